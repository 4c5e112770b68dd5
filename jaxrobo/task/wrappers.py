"""Functional wrappers: same ``reset(key, params)`` / ``step(state, action, params)`` interface, added behaviour.

Brax and MuJoCo Playground auto-reset to a cached first state, so every episode after the first starts the
same way; :class:`AutoReset` draws a fresh random initial state from the key carried in the state instead
(the single-env form of :mod:`jaxrobo.task.autoreset`, which the trainer and the Gymnasium vector env use batched).

Public surface: subclass :class:`Wrapper` (override ``reset`` / ``step``; everything else is forwarded to the
wrapped env); :class:`AutoReset`; :class:`CheckedActions` (the checked step: an out-of-range, NaN or fractional
action raises on the host, or is flagged in ``state.info["invalid_action"]`` under jit).
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core import rng, spaces
from jaxrobo.task.autoreset import where_done
from jaxrobo.task.env import Env, EnvState


class Wrapper(Env):
    """Forwards everything to the wrapped env."""

    def __init__(self, env: Env):
        self.env = env

    def __getattr__(self, name: str) -> Any:
        return getattr(self.env, name)

    def reset(self, key: jax.Array, params: Any = None) -> EnvState:
        return self.env.reset(key, params)

    def step(self, state: EnvState, action: jax.Array, params: Any = None) -> EnvState:
        return self.env.step(state, action, params)

    def action_space(self, params: Any = None):
        return self.env.action_space(params)

    def observation_space(self, params: Any = None):
        return self.env.observation_space(params)

    def state_bounds(self, params: Any = None):
        return self.env.state_bounds(params)


class AutoReset(Wrapper):
    """On ``done``, start a new episode from a fresh random initial state.

    The returned state keeps the finished step's ``reward``, ``terminated`` and ``truncated``; its ``obs`` is the
    new episode's first observation and ``info["final_obs"]`` the last observation of the finished one.
    """

    def reset(self, key: jax.Array, params: Any = None) -> EnvState:
        state = self.env.reset(key, params)
        return state.replace(info={**state.info, "final_obs": state.obs})

    def step(self, state: EnvState, action: jax.Array, params: Any = None) -> EnvState:
        inner = state.replace(info={k: v for k, v in state.info.items() if k != "final_obs"})
        stepped = self.env.step(inner, action, params)
        key, reset_key = rng.split(stepped.key)
        fresh = self.env.reset(reset_key, params)
        merged = where_done(stepped.done, fresh.replace(info=stepped.info), stepped)
        return merged.replace(reward=stepped.reward, terminated=stepped.terminated, truncated=stepped.truncated,
                              physics_nan=stepped.physics_nan, key=key,
                              info={**stepped.info, "final_obs": stepped.obs})


def action_is_valid(space: Any, action: Any) -> jax.Array:
    """Whether ``action`` is one env's valid action of ``space``, as a traceable bool: for ``Discrete(n)`` a whole
    number in ``0 .. n-1`` (a float that is integral counts), for a ``Box`` every entry finite and within its
    bounds."""
    a = jnp.asarray(action)
    if isinstance(space, spaces.Discrete):
        if jnp.issubdtype(a.dtype, jnp.integer):
            return (a >= 0) & (a < space.n)
        return jnp.isfinite(a) & (a == jnp.floor(a)) & (a >= 0) & (a < space.n)
    low, high = jnp.asarray(space.low), jnp.asarray(space.high)
    return jnp.all(jnp.isfinite(a) & (a >= low) & (a <= high))


class CheckedActions(Wrapper):
    """:meth:`jaxrobo.task.env.TaskEnv.step` with its action checked, for code whose actions may be bad.

    The plain step casts the action and uses it as is (its jit contract): ``7``, ``-1``, ``NaN`` or ``2.7`` on a
    4-action task act as some other action. Here a *concrete* action (called outside jit) that is not in the
    action space raises ``ValueError`` naming it and the space; under jit, where values cannot raise, the state's
    ``info["invalid_action"]`` says whether this step's action was invalid (the step itself is taken with the
    cast action, as the plain step would). ``reset`` adds the flag (False), so the state's structure is the same
    for every step (a ``lax.scan`` carry)."""

    FLAG = "invalid_action"

    def reset(self, key: jax.Array, params: Any = None) -> EnvState:
        state = self.env.reset(key, params)
        return state.replace(info={**state.info, self.FLAG: jnp.zeros((), bool)})

    def step(self, state: EnvState, action: jax.Array, params: Any = None) -> EnvState:
        space = self.env.action_space(params)
        if not isinstance(action, jax.core.Tracer):
            ok = bool(action_is_valid(space, np.asarray(action)))
            if not ok:
                allowed = (f"an integer in 0..{space.n - 1}" if isinstance(space, spaces.Discrete)
                           else f"finite values within [{space.low}, {space.high}]")
                raise ValueError(f"{type(self.env).__name__}.step: action={np.asarray(action).tolist()!r} is not in "
                                 f"the action space; expected {allowed}")
        valid = action_is_valid(space, action)
        stepped = self.env.step(state, action, params)
        return stepped.replace(info={**state.info, **stepped.info, self.FLAG: ~valid})
