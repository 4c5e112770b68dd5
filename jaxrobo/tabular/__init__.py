"""Tabular learning's pure pieces: the learner protocol and table helpers (:mod:`~jaxrobo.tabular.learner`) and
the observation discretiser (:mod:`~jaxrobo.tabular.discretise`). Learners (``agents/``) import the names below
from ``jaxrobo.tabular``: that is their stable surface."""
from jaxrobo.tabular.learner import (AgentParams, AgentState, Learner, argmax_random_ties, epsilon_greedy,
                                     epsilon_greedy_probabilities, greedy, greedy_probabilities, pick_among_maxima,
                                     row_argmax, row_max, row_min, row_pick)

__all__ = ["AgentParams", "AgentState", "Learner", "argmax_random_ties", "epsilon_greedy",
           "epsilon_greedy_probabilities", "greedy", "greedy_probabilities", "pick_among_maxima", "row_argmax",
           "row_max", "row_min", "row_pick"]
