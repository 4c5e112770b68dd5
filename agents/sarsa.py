"""Sarsa (the seed's ``Sarsa``): on-policy target ``r + gamma * Q(s', a')`` with the action ``a'`` taken next.

Exploration is uniform epsilon-greedy with random ties in both modes (that is what the seed's Sarsa does).
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxrobo.api import Learner, epsilon_greedy, row_pick


def target(key, q_next, a2, reward, discount, epsilon):
    return jnp.int32(0), reward + discount * row_pick(q_next[0], a2)


LEARNER = Learner("sarsa", epsilon_greedy, target, on_policy=True)
