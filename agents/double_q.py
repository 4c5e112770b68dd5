"""Double Q-learning (van Hasselt 2010): two tables; a coin picks the one to update, the other evaluates.

Target for table ``i``: ``r + gamma * Q_j(s', argmax_a Q_i(s', a))`` with ``j = 1 - i``; actions are chosen
epsilon-greedily on ``Q_0 + Q_1``. It removes Q-learning's maximisation bias.
"""
from __future__ import annotations

import jax.numpy as jnp

from jaxrobo.api import Learner, epsilon_greedy, rng, row_argmax


def target(key, q_next, a2, reward, discount, epsilon):
    table = rng.bernoulli(key).astype(jnp.int32)
    best = row_argmax(q_next[table])
    return table, reward + discount * q_next[1 - table, best]


LEARNER = Learner("double_q", epsilon_greedy, target, n_tables=2)
