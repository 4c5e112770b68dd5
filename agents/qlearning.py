"""Q-learning (the seed's ``QLearn``): target ``r + gamma * max_a' Q(s', a')``.

In seed-compat mode it explores as the seed does: with probability epsilon, add uniform noise in
``[-mag/2, mag/2)`` to every action value (``mag = max(|min Q|, |max Q|)``) and take the noisy argmax.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxrobo.api import Learner, argmax_random_ties, epsilon_greedy, rng, row_max, row_min


def noisy_greedy(key: jax.Array, q_row: jax.Array, epsilon: jax.Array) -> jax.Array:
    """The seed's QLearn.chooseAction (one uniform draw serves the coin, the noise and the tie-break)."""
    n = q_row.shape[-1]
    u = rng.uniform(key, (2 * n + 1,))
    mag = jnp.maximum(jnp.abs(row_min(q_row)), jnp.abs(row_max(q_row)))
    noisy = q_row + u[1:n + 1] * mag - 0.5 * mag
    return argmax_random_ties(jnp.where(u[0] < epsilon, noisy, q_row), u[n + 1:])


def select(key: jax.Array, q_row: jax.Array, epsilon: jax.Array, seed_compat: bool = False) -> jax.Array:
    return noisy_greedy(key, q_row, epsilon) if seed_compat else epsilon_greedy(key, q_row, epsilon)


def target(key, q_next, a2, reward, discount, epsilon):
    return jnp.int32(0), reward + discount * row_max(q_next[0])


LEARNER = Learner("qlearn", select, target)
