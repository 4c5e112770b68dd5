"""QuadcopterLiveShow: the seed's drone task, reproduced faithfully (seed 000, ``QuadcopterLiveShow-v0``).

Environment card
----------------
Actions      ``Discrete(5)``, the seed's Twist at ``speed_value`` (m/s, rad/s), tracked by the on-board controller
             for ``running_step`` s: 0 forward (vx = speed), 1 turn left (vx = 0.05, yaw rate = +speed),
             2 turn right (vx = 0.05, yaw rate = -speed), 3 up (vz = +speed), 4 down (vz = -speed).
Observation  ``[x]`` (m): the drone's x position only, as in the seed (which even fed the raw float to QLearn).
Reward       on failure -200; otherwise the seed's distance reward against the best distance so far in the
             episode (Euclidean, m, to ``(goal_x, goal_y, goal_z)``): +100 if closer than the best (which
             becomes the new best), 0 if equal, -100 otherwise. Then, every step including a failing one, the
             seed's action shaping: forward +100, left/right -50, up -150, down -50.
Termination  failure only: altitude > ``max_altitude`` (m) or |roll| or |pitch| >= ``max_incl`` (rad). Reaching
             the goal does not end the episode (the seed had no arrival test). Truncation at
             ``max_episode_steps`` (the seed's ``timestep_limit`` 100).
Reset        hovering at rest at ``(init_x, init_y, init_z)`` heading +x (the seed's take-off); the best distance
             starts as the distance from there (the seed's ``init_desired_pose``).
Physics      ``assets/quadcopter.xml`` on ``backend`` (``mjx`` or ``rigid``) at ``timestep`` s; the on-board
             altitude floor ``min_altitude`` (m) keeps down commands from reaching the ground, as the AR.Drone's
             firmware did in the seed's Gazebo world (which had a floor; jaxrobo's physics has no contacts).
Parameters   see :class:`Options` (static) and :class:`Params` (numbers; vmappable).

The seed reports that this task does not learn; jaxrobo keeps it as it was (see ``docs/quadcopter.md``) and
adds :mod:`envs.quadcopter.goto`, the seed's own list of fixes.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs.quadcopter.robot import QuadcopterOptions, QuadcopterTask, twist_command
from jaxrobo.api import BaseParams, param, pytree_dataclass, spaces

#: The seed's action shaping, added to every step's reward: forward, left, right, up, down.
ACTION_SHAPING = (100.0, -50.0, -50.0, -150.0, -50.0)


@pytree_dataclass
class Options(QuadcopterOptions):
    min_altitude: float = param(0.2, low=0.0, high=2.0, static=True, unit="m",
                                doc="on-board altitude floor of descent commands (the seed's world had a floor)")


@pytree_dataclass
class Params(BaseParams):
    max_episode_steps: int = param(100, low=1, unit="steps", doc="the seed's timestep_limit")
    speed_value: float = param(1.0, low=0.0, low_open=True, high=5.0, unit="m/s or rad/s", doc="Twist magnitude")
    goal_x: float = param(14.0, low=-100.0, high=100.0, unit="m", doc="desired_pose x")
    goal_y: float = param(1.0, low=-100.0, high=100.0, unit="m", doc="desired_pose y")
    goal_z: float = param(0.7, low=0.0, high=10.0, unit="m", doc="desired_pose z")
    max_altitude: float = param(2.0, low=0.0, low_open=True, high=100.0, unit="m")
    max_incl: float = param(0.7, low=0.0, low_open=True, high=1.6, unit="rad", doc="roll/pitch limit")
    init_x: float = param(0.0, low=-100.0, high=100.0, unit="m")
    init_y: float = param(0.0, low=-100.0, high=100.0, unit="m")
    init_z: float = param(1.0, low=0.0, high=10.0, unit="m", doc="altitude after take-off")
    x_low: float = param(-5.0, low=-1000.0, high=1000.0, unit="m", doc="discretiser range of x (low)")
    x_high: float = param(20.0, low=-1000.0, high=1000.0, unit="m", doc="discretiser range of x (high)")


@pytree_dataclass
class TaskVars:
    """Per-episode variables: the best distance to the goal so far (the seed's ``best_dist``)."""

    best_dist: jax.Array


class QuadcopterLiveShow(QuadcopterTask):
    Options = Options
    Params = Params
    #: None: with x alone observed the task cannot learn to reach the goal, as in the seed (docs/quadcopter.md).
    learning_target = None

    def observation_space(self, params: Params | None = None) -> spaces.Box:
        return spaces.Box(np.full(1, -np.inf, np.float32), np.full(1, np.inf, np.float32), ("x",))

    def state_bounds(self, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self.default_params if params is None else params
        return np.array([float(p.x_low)], np.float32), np.array([float(p.x_high)], np.float32)

    @staticmethod
    def _goal(params: Params) -> jax.Array:
        return jnp.stack([params.goal_x, params.goal_y, params.goal_z]).astype(jnp.float32)

    # ---- the seed's hooks -------------------------------------------------------------------------------
    def _set_init_pose(self, key: jax.Array, params: Params) -> tuple[jax.Array, jax.Array]:
        return self.robot.init_pose(jnp.stack([params.init_x, params.init_y, params.init_z]), 0.0)

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> TaskVars:
        pos = self.robot.read_sensors(pipeline_state)["pos"]
        return TaskVars(jnp.linalg.norm(pos - self._goal(params)))

    def _set_action(self, action: jax.Array, task: TaskVars, params: Params) -> tuple[jax.Array, TaskVars]:
        return twist_command(action, params.speed_value), task

    def _get_obs(self, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return self.robot.read_sensors(pipeline_state)["pos"][:1].astype(jnp.float32)

    def _failed(self, pipeline_state: Any, params: Params) -> jax.Array:
        s = self.robot.read_sensors(pipeline_state)
        roll, pitch = s["rpy"][0], s["rpy"][1]
        incl_bad = (jnp.abs(roll) >= params.max_incl) | (jnp.abs(pitch) >= params.max_incl)
        return (s["pos"][2] > params.max_altitude) | incl_bad

    def _is_done(self, obs: jax.Array, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return self._failed(pipeline_state, params)

    def _compute_reward(self, obs, done, action, pipeline_state, task, params) -> tuple[jax.Array, TaskVars]:
        dist = jnp.linalg.norm(self.robot.read_sensors(pipeline_state)["pos"] - self._goal(params))
        closer = dist < task.best_dist
        distance_reward = jnp.where(closer, 100.0, jnp.where(dist == task.best_dist, 0.0, -100.0))
        failed = self._failed(pipeline_state, params)
        reward = jnp.where(failed, -200.0, distance_reward) + jnp.asarray(ACTION_SHAPING)[action]
        best = jnp.where(closer & ~failed, dist, task.best_dist)
        return reward.astype(jnp.float32), TaskVars(best)
