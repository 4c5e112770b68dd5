"""Resolve a training run from the shipped YAML files and user overrides, validated before anything compiles.

A task's agent YAML (``agents/configs/<name>.yaml``) holds presets; each preset maps learner parameters
(:class:`agents.tabular.AgentParams`) and loop settings (:class:`jaxrobo.train.TrainConfig`), plus an optional
``env:`` mapping of env overrides. ``default`` is the textbook setup that learns; ``seed`` is the seed's own
values with its learners reproduced exactly.

Overrides are ``{key: value}``; a bare key goes to whichever of learner, loop or env declares it (learner
and loop first), ``env.KEY`` forces the env and ``agent.KEY`` the learner/loop.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Any, Mapping

from agents.tabular import AgentParams
from jaxrobo.config import ConfigError, as_dict, load_yaml, split_and_validate, unknown_key
from jaxrobo.env import Env
from jaxrobo.registry import _lookup, make
from jaxrobo.struct import rules
from jaxrobo.train import TrainConfig

AGENT_CONFIG_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "agents", "configs")


@dataclasses.dataclass(frozen=True)
class RunSpec:
    env_id: str
    preset: str
    env: Env
    agent_params: AgentParams
    config: TrainConfig
    env_overrides: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration, as written to ``config.yaml`` of a run."""
        return {
            "env_id": self.env_id,
            "preset": self.preset,
            "env_options": as_dict(self.env.options),
            "env_params": as_dict(self.env.default_params),
            "agent_params": as_dict(self.agent_params),
            "train": as_dict(self.config),
        }


def agent_presets(env_id: str) -> dict[str, dict[str, Any]]:
    """The presets in the id's agent YAML (``{}`` if it has none)."""
    spec = _lookup(env_id).spec
    if not spec.agent_config:
        return {}
    path = spec.agent_config
    if not os.path.isabs(path):
        path = os.path.join(AGENT_CONFIG_DIR, path)
    return load_yaml(path)


def resolve(env_id: str, preset: str = "default", overrides: Mapping[str, Any] | None = None,
            agent: str | None = None) -> RunSpec:
    """Build env, learner parameters and loop config for a run; raises :class:`ConfigError` on any bad value."""
    presets = agent_presets(env_id)
    if presets and preset not in presets:
        raise ConfigError(f"{env_id}: preset={preset!r}: allowed values are {', '.join(presets)}")
    chosen = dict(presets.get(preset, {}) or {})
    env_values = dict(chosen.pop("env", {}) or {})
    agent_values = chosen
    env_cls = _lookup(env_id).env_class()
    env_keys = set(rules(env_cls.Options)) | set(rules(env_cls.Params))
    agent_keys = set(rules(AgentParams)) | set(rules(TrainConfig))
    for key, value in (overrides or {}).items():
        if key.startswith("env."):
            env_values[key[4:]] = value
        elif key.startswith("agent."):
            agent_values[key[6:]] = value
        elif key in agent_keys:
            agent_values[key] = value
        elif key in env_keys:
            env_values[key] = value
        else:
            raise unknown_key(key, agent_keys | env_keys, where="--set")
    if agent is not None:
        agent_values["agent"] = agent
    where = f"{env_id} preset {preset}"
    agent_kw, train_kw = split_and_validate(agent_values, AgentParams, TrainConfig, where=where)
    env = make(env_id, **env_values)
    return RunSpec(env_id, preset, env, AgentParams(**agent_kw), TrainConfig(**train_kw), env_values)
