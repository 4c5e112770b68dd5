"""MyPendulum: keep a torque-driven pendulum upright (the task half of the template; the robot is ``my_robot.py``).

Environment card
----------------
Actions      ``Discrete(3)``: the motor torque for the next control step, 0 ``-max_torque``, 1 zero,
             2 ``+max_torque`` (N m; the MJCF clamps it to +-2 N m).
Observation  ``[angle (rad, 0 = upright, + towards +x), angular_velocity (rad/s)]``.
Reward       1.0 every step, including the step on which the episode terminates.
Termination  ``|angle| >= max_angle``. Truncation at ``max_episode_steps`` (200 in ``my_task.yaml``; the
             class default is 1000).
Control      one step holds the torque for ``running_step`` s (0.05), i.e. ``running_step / timestep`` physics
             steps.
Reset        angle ``init_angle`` (rad) and angular velocity 0, each plus uniform noise in ``+-init_noise``.
Parameters   :class:`Options` (static: model and code path): ``backend``, ``running_step`` (s), ``timestep``
             (s). :class:`Params` (numbers, vmappable): ``max_torque`` (N m), ``max_angle`` (rad),
             ``init_angle`` (rad), ``init_noise`` (rad, rad/s), ``vel_bound`` (rad/s, the discretiser's range
             of the angular velocity), ``max_episode_steps`` (steps).

Registered at the bottom of this file as ``MyPendulum-v0``; ``jaxrobo train --env my_task:MyPendulum-v0`` imports
this module (from the current directory) and trains it; its env YAML and agent presets are the files beside it.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import jaxrobo
from jaxrobo.api import BaseParams, TaskEnv, param, pytree_dataclass, rng, spaces
from my_robot import BACKENDS, PendulumRobot

#: Action ``i`` applies ``TORQUE_SIGNS[i] * max_torque``.
TORQUE_SIGNS = (-1.0, 0.0, 1.0)


@pytree_dataclass
class Options:
    backend: str = param("mjx", choices=BACKENDS, static=True, doc="physics engine")
    running_step: float = param(0.05, low=0.0, low_open=True, high=1.0, static=True, unit="s",
                                doc="control period")
    timestep: float = param(0.01, low=0.0, low_open=True, high=0.05, static=True, unit="s", doc="physics step")


@pytree_dataclass
class Params(BaseParams):
    max_torque: float = param(1.5, low=0.0, low_open=True, high=2.0, unit="N m", doc="torque of actions 0 and 2")
    max_angle: float = param(0.5, low=0.0, low_open=True, high=3.2, unit="rad", doc="fails beyond +-max_angle")
    init_angle: float = param(0.0, low=-3.2, high=3.2, unit="rad", doc="angle at reset")
    init_noise: float = param(0.05, low=0.0, high=1.0, doc="uniform noise on angle (rad) and velocity (rad/s)")
    vel_bound: float = param(3.0, low=0.0, low_open=True, unit="rad/s", doc="discretiser range of the velocity")


@pytree_dataclass
class TaskVars:
    """Per-episode variables: none beyond the physics (a task keeps e.g. a goal or a command here)."""

    steps_up: jax.Array


class MyPendulum(TaskEnv):
    Options = Options
    Params = Params

    def __init__(self, options: Options | None = None, params: Params | None = None):
        super().__init__(options, params)
        o = self.options
        self.robot = PendulumRobot(o.backend, o.running_step, o.timestep)
        self._signs = jnp.asarray(TORQUE_SIGNS, jnp.float32)

    def action_space(self, params: Params | None = None) -> spaces.Discrete:
        return spaces.Discrete(len(TORQUE_SIGNS))

    def observation_space(self, params: Params | None = None) -> spaces.Box:
        inf = np.full(2, np.inf, np.float32)
        return spaces.Box(-inf, inf, ("angle", "angular_velocity"))

    def state_bounds(self, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self.default_params if params is None else params
        high = np.array([float(p.max_angle), float(p.vel_bound)], np.float32)  # numpy: on the host, no compile
        return -high, high

    def _set_init_pose(self, key: jax.Array, params: Params) -> tuple[jax.Array, jax.Array]:
        noise = rng.uniform(key, (2,), -params.init_noise, params.init_noise)
        return self.robot.init_pose(params.init_angle + noise[0], noise[1])

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> TaskVars:
        return TaskVars(steps_up=jnp.zeros((), jnp.int32))

    def _set_action(self, action: jax.Array, task: TaskVars, params: Params) -> tuple[jax.Array, TaskVars]:
        return (self._signs[action] * params.max_torque)[None], TaskVars(task.steps_up + 1)

    def _get_obs(self, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return self.robot.read_sensors(pipeline_state).astype(jnp.float32)

    def _is_done(self, obs: jax.Array, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return jnp.abs(obs[0]) >= params.max_angle

    def _compute_reward(self, obs, done, action, pipeline_state, task, params) -> tuple[jax.Array, TaskVars]:
        return jnp.ones((), jnp.float32), task


# The YAML paths are relative to this file's directory (absolute paths work too).
jaxrobo.register("MyPendulum-v0", MyPendulum, config="my_task.yaml", agent_config="my_task_agent.yaml",
                 description="custom-task template: keep a torque-driven pendulum upright, 3 actions")
