"""Autoreset: a fresh episode, from fresh randomness, wherever an episode is done, and nothing else changed.

One definition serves the three places that start new episodes inside a compiled loop: the trainer
(:meth:`jaxrobo.training.trainer.Trainer.step`), the Gymnasium vector env
(:class:`jaxrobo.interop.gym_adapter.JaxroboVectorEnv`) and the :class:`jaxrobo.task.wrappers.AutoReset` wrapper. Each
passes the keys its envs reset from; this module only decides which envs take the fresh values and how they are
computed.

Public surface:

:func:`where_done` ``(done, fresh, current)``
    The fresh values where ``done``, the current ones elsewhere, leaf by leaf (``done`` broadcast over each
    leaf's trailing axes). The single-env form: ``done`` may be a scalar.
:func:`autoreset` ``(env, done, keys, params, stepped, capacity=None)``
    A batch of env states with ``env.reset(keys[i], params)`` wherever ``done[i]``.
:func:`reset_where` ``(reset, done, keys, current, capacity=None)``
    The same for any values derived from a reset (the trainer also resets each env's discretised state and
    table rows): ``reset(keys, envs)`` computes them for a batch of keys, ``envs`` being the indices of those
    envs in the batch (None: the whole batch, in order).

``capacity``: a reset draws random numbers and builds a physics state, and under ``vmap`` a plain select pays
for it in every env every step although few are done. With ``capacity < len(done)`` the done envs (at most
``capacity`` of them) are gathered, reset and scattered back, and a step with more done envs resets the whole
batch and selects; without it (None, or ``>= len(done)``) every step resets the whole batch and selects. Both
give the same values: each env resets from its own key either way. Where the gather pays off is a speed choice
of the execution plan (a CPU gains, an accelerator loses); this module takes it as an argument. Under an outer
``vmap`` (a sweep) the branch between the two becomes a select that computes both.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from jaxrobo.task.env import Env

__all__ = ["where_done", "reset_where", "autoreset"]


def where_done(done: jax.Array, fresh: Any, current: Any) -> Any:
    """``fresh`` where ``done``, else ``current``: two pytrees of the same structure, leaves ``[*done.shape, ...]``."""
    def pick(new, old):
        return jnp.where(jnp.reshape(done, done.shape + (1,) * (jnp.ndim(old) - jnp.ndim(done))), new, old)

    return jax.tree.map(pick, fresh, current)


ResetFn = Callable[[jax.Array, "jax.Array | None"], Any]


def reset_where(reset: ResetFn, done: jax.Array, keys: jax.Array, current: Any, capacity: int | None = None) -> Any:
    """``current`` (a pytree of ``[n, ...]`` leaves) with ``reset``'s fresh values wherever ``done`` (``[n]``).

    ``reset(keys, envs)`` returns the fresh values (same structure as ``current``) for a batch of keys: the whole
    batch's ``keys`` with ``envs=None``, or ``keys[envs]`` for the gathered envs ``envs`` (int32 indices, clipped
    into the batch; the padding rows are dropped when scattered back). The env ``i`` always resets from
    ``keys[i]``, so the values do not depend on ``capacity``."""
    n = done.shape[0]

    def everyone(_):
        return where_done(done, reset(keys, None), current)

    if capacity is None or capacity >= n:
        return everyone(None)

    # Where each done env goes in the compacted list: one running count (``jnp.nonzero`` takes two and a
    # histogram for the same list).
    slot = jnp.cumsum(done, dtype=jnp.int32) - 1

    def only_done(_):
        # The done envs in order, padded with n (dropped by the scatters below).
        rows = jnp.full(capacity, n, jnp.int32).at[jnp.where(done, slot, capacity)].set(
            jnp.arange(n, dtype=jnp.int32), mode="drop")
        envs = jnp.minimum(rows, n - 1)
        fresh = reset(keys[envs], envs)
        return jax.tree.map(lambda old, new: old.at[rows].set(new, mode="drop"), current, fresh)

    return jax.lax.cond(slot[-1] >= capacity, everyone, only_done, None)


def autoreset(env: Env, done: jax.Array, keys: jax.Array, params: Any, stepped: Any,
              capacity: int | None = None) -> Any:
    """The batch of env states ``stepped`` with ``env.reset(keys[i], params)`` wherever ``done[i]``."""
    return reset_where(lambda k, _envs: jax.vmap(env.reset, in_axes=(0, None))(k, params), done, keys, stepped,
                       capacity)
