"""Functional wrappers: same ``reset(key, params)`` / ``step(state, action, params)`` interface, added behaviour.

Brax and MuJoCo Playground auto-reset to a cached first state, so every episode after the first starts the
same way; :class:`AutoReset` draws a fresh random initial state from the key carried in the state instead
(the single-env form of :mod:`jaxrobo.task.autoreset`, which the trainer and the Gymnasium vector env use batched).

Public surface: subclass :class:`Wrapper` (override ``reset`` / ``step``; everything else is forwarded to the
wrapped env); :class:`AutoReset`.
"""
from __future__ import annotations

from typing import Any

import jax

from jaxrobo.core import rng
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
