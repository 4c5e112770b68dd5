"""The robot half of the template: a one-joint pendulum (``pendulum.xml`` beside this file) driven by a torque
motor, with its joint sensors. Copy it and change the MJCF, the joints it reads and the controller.

A robot loads its MJCF, builds its simulator with :func:`jaxrobo.make_simulator` (MuJoCo MJX here; a robot may
also offer a hand-written backend, see ``envs/cartpole/robot.py``) and says what it senses. It knows nothing of the
task: actions, rewards and episode ends are the task's (``my_task.py``).
"""
from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import mujoco

from jaxrobo.api import Robot, backend_choices, load_model, make_simulator

MJCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "pendulum.xml")
JOINT = "hinge"
#: The physics engines this robot runs on (MJX first: the default).
BACKENDS = backend_choices()


class PendulumRobot(Robot):
    """A rod on a hinge; the command is the motor torque (N m), applied as it is every physics substep."""

    def __init__(self, backend: str = "mjx", running_step: float = 0.05, timestep: float = 0.01):
        mj_model = load_model(MJCF, timestep=timestep)
        # What MJX integrates: the same model without its light and camera (same dynamics, less work).
        physics = lambda: load_model(MJCF, timestep=timestep, physics_only=True)  # noqa: E731
        super().__init__(make_simulator(mj_model, backend, running_step, physics))
        joint = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, JOINT)
        self.q, self.v = int(mj_model.jnt_qposadr[joint]), int(mj_model.jnt_dofadr[joint])

    def init_pose(self, angle: jax.Array, angular_velocity: jax.Array = 0.0) -> tuple[jax.Array, jax.Array]:
        """``(qpos, qvel)`` for a rod angle (rad, 0 = up) and angular velocity (rad/s)."""
        return jnp.zeros(1).at[self.q].set(angle), jnp.zeros(1).at[self.v].set(angular_velocity)

    def read_sensors(self, pipeline_state: Any) -> jax.Array:
        """``[angle (rad), angular_velocity (rad/s)]``."""
        q, v = self.sim.qpos(pipeline_state), self.sim.qvel(pipeline_state)
        return jnp.stack([q[self.q], v[self.v]])
