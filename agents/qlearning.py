"""Q-learning (the seed's ``QLearn``): target ``r + gamma * max_a' Q(s', a')``.

In seed-compat mode it explores as the seed does: with probability epsilon, add uniform noise in
``[-mag/2, mag/2)`` to every action value (``mag = max(|min Q|, |max Q|)``) and take the noisy argmax.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from agents.tabular import Learner, epsilon_greedy, greedy


def noisy_greedy(key: jax.Array, q_row: jax.Array, epsilon: jax.Array) -> jax.Array:
    """The seed's QLearn.chooseAction."""
    k_explore, k_noise, k_tie = jax.random.split(key, 3)
    mag = jnp.maximum(jnp.abs(jnp.min(q_row)), jnp.abs(jnp.max(q_row)))
    noisy = q_row + jax.random.uniform(k_noise, q_row.shape) * mag - 0.5 * mag
    explore = jax.random.uniform(k_explore) < epsilon
    return greedy(k_tie, jnp.where(explore, noisy, q_row))


def select(key: jax.Array, q_row: jax.Array, epsilon: jax.Array, seed_compat: bool = False) -> jax.Array:
    return noisy_greedy(key, q_row, epsilon) if seed_compat else epsilon_greedy(key, q_row, epsilon)


def target(key, q, s2, a2, reward, discount, epsilon):
    return jnp.int32(0), reward + discount * jnp.max(q[0, s2])


LEARNER = Learner("qlearn", select, target)
