"""Expected Sarsa: target ``r + gamma * E_pi[Q(s', .)]`` under the epsilon-greedy policy itself.

It averages out the randomness of the next action, so it learns like Sarsa with less variance.
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxrobo.api import Learner, epsilon_greedy, epsilon_greedy_probabilities


def target(key, q_next, a2, reward, discount, epsilon):
    row = q_next[0]
    return jnp.int32(0), reward + discount * jnp.dot(epsilon_greedy_probabilities(row, epsilon), row)


LEARNER = Learner("expected_sarsa", epsilon_greedy, target)
