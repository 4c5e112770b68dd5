"""QuadcopterGotoTwist: the Goto task flown with a continuous Twist (for Brax's PPO/SAC).

The same episodes as :mod:`envs.quadcopter.goto` (random goals, the obstacle between start and goal, sonar,
reward, termination); only the action differs: the whole Twist instead of the seed's five fixed ones.

Environment card
----------------
Actions      ``Box(-1, 1, shape=(4,))``, float32: the Twist ``[vx, vy, vz, yaw_rate]`` (heading frame; m/s and
             rad/s) is ``speed_value * a`` (``a`` clipped to [-1, 1]), so each component is bounded by
             ``speed_value``; held for ``running_step`` s and tracked by the on-board controller. Normalised to
             [-1, 1] because Brax's policies (tanh-squashed) and Gymnasium's checker expect it; ``speed_value``
             is a traced parameter, so the bound can be vmapped without changing the space.
Observation  as :mod:`envs.quadcopter.goto`: ``[goal_dist, goal_bearing, goal_dz, sonar_forward, sonar_left,
             sonar_right, sonar_down]``, raw float32 (no discretisation).
Reward       as :mod:`envs.quadcopter.goto`.
Termination  as :mod:`envs.quadcopter.goto` (arrival, crash, workspace, altitude and inclination limits).
             Truncation at ``max_episode_steps`` (100).
Success      ``TaskVars.arrived``; :meth:`QuadcopterGotoTwist.step_metrics` reports it per step as ``arrived``
             (so Brax's evaluation reports ``eval/episode_arrived``, the share of arriving episodes).
Physics      ``rigid`` by default (closed-form Newton-Euler, fastest); ``mjx`` as in the discrete id.
Parameters   :class:`envs.quadcopter.goto.Options` and :class:`envs.quadcopter.goto.Params`.
"""
from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from envs.quadcopter.goto import Options, Params, QuadcopterGoto, TaskVars
from jaxrobo.api import EnvState, spaces

TWIST_NAMES = ("vx", "vy", "vz", "yaw_rate")


class QuadcopterGotoTwist(QuadcopterGoto):
    """:class:`envs.quadcopter.goto.QuadcopterGoto` with a ``Box(-1, 1, (4,))`` Twist action."""

    Options = Options
    Params = Params
    action_dtype = jnp.float32
    #: The discrete ids this task is the continuous counterpart of (named by the Brax adapter's refusal).
    continuous_of: ClassVar[tuple[str, ...]] = ("QuadcopterGoto-v1",)
    #: The host step takes an action index (the adapter's engine="numpy" steps Discrete tasks only).
    host_step = None

    def action_space(self, params: Params | None = None) -> spaces.Box:
        one = np.ones(len(TWIST_NAMES), np.float32)
        return spaces.Box(-one, one, TWIST_NAMES)

    def _set_action(self, action: jax.Array, task: TaskVars, params: Params) -> tuple[jax.Array, TaskVars]:
        a = jnp.clip(jnp.reshape(action, (-1,))[: len(TWIST_NAMES)], -1.0, 1.0)
        return (params.speed_value * a).astype(jnp.float32), task

    def step_metrics(self, state: EnvState, params: Any = None) -> dict[str, jax.Array]:
        """Per-step numbers whose sum over an episode means something: ``arrived`` (1 on the arriving step)
        and ``crashed`` (1 on a crash step)."""
        return {"arrived": state.task.arrived.astype(jnp.float32),
                "crashed": state.task.crashed.astype(jnp.float32)}


__all__ = ["QuadcopterGotoTwist", "Options", "Params", "TaskVars"]
