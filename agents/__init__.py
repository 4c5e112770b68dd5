"""Tabular learners, each a small module of pure functions (see :mod:`jaxrobo.tabular`)."""
from __future__ import annotations

from agents import double_q, expected_sarsa, qlearning, sarsa
from jaxrobo.api import AgentParams, AgentState, Learner

LEARNERS: dict[str, Learner] = {m.LEARNER.name: m.LEARNER for m in (qlearning, sarsa, expected_sarsa, double_q)}


def get(name: str) -> Learner:
    """The learner called ``name`` (``qlearn``, ``sarsa``, ``expected_sarsa``, ``double_q``)."""
    if name not in LEARNERS:
        raise ValueError(f"agent={name!r}: allowed values are {', '.join(LEARNERS)}")
    return LEARNERS[name]


__all__ = ["AgentParams", "AgentState", "Learner", "LEARNERS", "get"]
