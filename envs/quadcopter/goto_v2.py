"""QuadcopterGoto-v2: the Goto homework (random goal, obstacle, sonar) made learnable by every tabular run.

Environment card
----------------
Same task as ``QuadcopterGoto-v1`` (:mod:`envs.quadcopter.goto`: actions, reset, obstacles, sonar, termination,
success), with these differences, each fixing a reason why most v1 runs plateaued (docs/quadcopter.md):

Observation  v1's seven values plus ``goal_clear`` (m): how far the straight flight towards the goal is free,
             i.e. the level ray from the drone towards the goal against the obstacles *grown by*
             ``drone_radius + clear_margin`` (so "free" means the drone's whole body passes), clipped to
             ``sonar_range``; an obstacle beyond the goal does not count (free up to the goal reads
             ``sonar_range``). v1's forward sonar looks along the heading only: whether to head for the goal or
             go round the obstacle depended on where the drone had been, which a memoryless table cannot hold;
             ``goal_clear`` makes that choice a function of the state. ``goal_dz`` is read where the current
             climb or descent stops, ``goal_dz - dz_lead * vz`` (``dz_lead`` 0.25 s, the vertical velocity
             loop's time constant): an "up" or "down" step goes on for ~0.17 m after its command ends, and a
             table that sees no velocity mistook that motion for standing still, so greedy flights cycled
             up/down across the level band 1-1.5 m from the goal (v1's ``goal_dz`` is the drone's own).
Reward       v1's terms with three changes. ``crash_penalty`` 150 (v1 50): at 50 a crash cost less than the
             steps of a detour (``step_cost`` 2 each), so diving into the obstacle or the ground was the cheap way
             out of a hard start. ``altitude_cost`` 0 (v1 0.5 per m and step): the table sees altitude only as
             ``goal_dz`` and a low/high bin, so paying for altitude made sinking inside a bin pay and greedy
             flights cycled up and down. Two shaping terms, each the change of a potential (so over any loop
             they sum to zero and a loop still costs its steps): ``heading_reward`` per rad the goal bearing's
             magnitude shrank and ``climb_reward`` per m ``|goal_dz|`` shrank: turning or climbing towards the
             goal pays at once, instead of only through the progress a later forward step makes, which aliased
             bins blurred into left/right and up/down cycles. ``climb_reward``'s potential is the observed
             ``goal_dz`` (where the climb stops), so a climb pays when commanded, not a step later.
Discretiser  ``state_bounds`` cover ``goal_clear`` like the sonars (``sonar_bound``); the agent preset
             (``agents/configs/quadcopter_goto_v2.yaml``) cuts every dimension at explicit edges and learns
             with ``alpha`` 0.05 (not 0.2), so that the table frozen after training does not keep a greedy
             choice that the last updates were still swapping between close action values.
Parameters   :class:`Params` adds ``clear_margin``, ``heading_reward``, ``climb_reward``, ``dz_lead``; the rest (and
             :class:`Options`) as v1's.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs.quadcopter import goto_step
from envs.quadcopter.goto import OBS_NAMES as V1_OBS_NAMES
from envs.quadcopter.goto_step import kinds_of
from envs.quadcopter.robot import fold_obstacles
from envs.quadcopter.goto import Options, QuadcopterGoto, TaskVars
from envs.quadcopter.goto import Params as V1Params
from jaxrobo.api import EnvState, param, pytree_dataclass, spaces

OBS_NAMES = V1_OBS_NAMES + ("goal_clear",)


@pytree_dataclass
class Params(V1Params):
    altitude_cost: float = param(0.0, low=0.0, high=1e4, unit="1/m",
                                 doc="0: the table sees altitude only as goal_dz and a low/high bin, so paying for "
                                     "it made sinking inside a bin pay and flights cycle up and down")
    crash_penalty: float = param(150.0, low=0.0, high=1e5,
                                 doc="above a detour's step costs, so crashing is never the cheap way out")
    clear_margin: float = param(0.1, low=0.0, high=10.0, unit="m",
                                doc="goal_clear: obstacles grown by drone_radius + this")
    heading_reward: float = param(5.0, low=0.0, high=1e4, unit="1/rad",
                                  doc="per rad the goal bearing |shrank| this step: turning towards the goal pays")
    climb_reward: float = param(5.0, low=0.0, high=1e4, unit="1/m",
                                doc="per m the goal altitude difference |shrank| this step: climbing towards it pays")
    dz_lead: float = param(0.25, low=0.0, high=10.0, unit="s",
                           doc="goal_dz is read where the climb stops: goal_dz - dz_lead * vertical velocity (the "
                               "vertical velocity loop's time constant, 1 / ControllerGains.k_vel_z; 0: v1's goal_dz)")


@pytree_dataclass
class TaskVars2(TaskVars):
    """v1's per-episode variables and the last goal bearing and altitude difference (for the shaping terms)."""

    prev_bearing: jax.Array
    prev_dz: jax.Array


class QuadcopterGoto2(QuadcopterGoto):
    Options = Options
    Params = Params
    step_kernel_variant = "v2"
    v2 = True

    def observation_space(self, params: Params | None = None) -> spaces.Box:
        n = len(OBS_NAMES)
        return spaces.Box(np.full(n, -np.inf, np.float32), np.full(n, np.inf, np.float32), OBS_NAMES)

    def state_bounds(self, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self.default_params if params is None else params
        low, high = super().state_bounds(p)
        return np.append(low, np.float32(0.0)), np.append(high, np.float32(float(p.sonar_bound)))

    def _goal_clear(self, pos: jax.Array, task: TaskVars, params: Params) -> jax.Array:
        """Free length of the level flight from ``pos`` towards the goal: the observation's ``goal_clear``
        (:func:`envs.quadcopter.goto_step.observe`)."""
        goal = [task.goal[i] for i in range(3)]
        zero = 0.0 * pos[0]
        obs, _, _ = goto_step.observe(jnp, [pos[i] for i in range(3)], zero, zero, goal, self._p(params), True,
                                      kinds_of(self.options.obstacle_kind),
                                      lambda distances, init: fold_obstacles(task.obstacles, distances, init))
        return obs[-1]

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> TaskVars2:
        task = super()._init_env_variables(key, pipeline_state, params)
        obs = super()._get_obs(pipeline_state, task, params)
        fields = {f.name: getattr(task, f.name) for f in dataclasses.fields(task)}
        # At reset the drone hovers at rest: goal_dz's lead adds nothing.
        return TaskVars2(**fields, prev_bearing=jnp.abs(obs[1]), prev_dz=jnp.abs(obs[2]))


__all__ = ["QuadcopterGoto2", "Options", "Params", "TaskVars", "TaskVars2", "EnvState", "OBS_NAMES"]
