"""CartPoleContinuous: keep the pole up with a continuous, bounded cart command (for Brax's PPO/SAC).

The same robot, reset, termination and reward as :mod:`envs.cartpole.stay_up`; only the action differs: one real
number instead of the seed's increments, applied directly (no accumulated command).

Environment card
----------------
Actions      ``Box(-1, 1, shape=(1,))``, float32. The command is ``max_command * a`` (``a`` clipped to [-1, 1]):
             a force on the cart in N (``control_type="effort"``, the default) or the cart's velocity set-point in
             m/s (``control_type="velocity"``). Normalised to [-1, 1] because Brax's policies (tanh-squashed)
             and Gymnasium's checker both expect it; ``max_command`` is a traced parameter, so the bound can be
             vmapped without changing the space.
Observation  ``[cart_x (m), cart_v (m/s), pole_angle (rad), pole_angular_velocity (rad/s)]``, raw float32 (no
             rounding, no discretisation).
Reward       1.0 every step, including the step on which the episode terminates.
Termination  ``cart_x`` outside ``(min_base_pose_x, max_base_pose_x)`` or the pole angle outside
             ``(min_pole_angle, max_pole_angle)``. Truncation at ``max_episode_steps`` (1000).
Control      the command is held for ``running_step`` s (0.04), i.e. ``running_step / timestep`` physics steps.
Reset        cart at ``init_pos``, pole at ``init_pole_angle``, each state variable plus uniform noise in
             ``±init_noise``.
Physics      ``analytic`` by default (the closed form, fastest); ``mjx`` and Brax's pipelines as in the
             discrete ids.
Parameters   see :class:`Options` (static) and :class:`Params` (numbers; vmappable).
"""
from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from envs.cartpole.robot import BACKENDS, CartPoleRobot
from envs.cartpole.stay_up import CartPoleStayUp
from jaxrobo.api import BaseParams, LearningTarget, param, pytree_dataclass, spaces


@pytree_dataclass
class Options:
    control_type: str = param("effort", choices=("effort", "velocity"), static=True,
                              doc="what the command is: a force on the cart (N) or its velocity set-point (m/s)")
    backend: str = param("analytic", choices=BACKENDS, static=True,
                         doc="physics: 'analytic' (closed form, fastest), 'mjx' or a Brax pipeline")
    running_step: float = param(0.04, low=0.0, low_open=True, high=1.0, static=True, unit="s",
                                doc="control period")
    timestep: float = param(0.01, low=0.0, low_open=True, high=0.04, static=True, unit="s", doc="physics step")


@pytree_dataclass
class Params(BaseParams):
    max_command: float = param(10.0, low=0.0, low_open=True, high=1000.0, unit="N or m/s",
                               doc="command at action ±1 (10 N moves the 1.1 kg cart-pole at ~9 m/s^2)")
    min_pole_angle: float = param(-0.7, low=-3.2, high=0.0, unit="rad", doc="-40 deg, the seed's limit")
    max_pole_angle: float = param(0.7, low=0.0, high=3.2, unit="rad", doc="+40 deg, the seed's limit")
    min_base_pose_x: float = param(-2.5, low=-100.0, high=0.0, unit="m")
    max_base_pose_x: float = param(2.5, low=0.0, high=100.0, unit="m")
    init_pos: float = param(0.0, low=-100.0, high=100.0, unit="m", doc="cart position at reset",
                            within=("min_base_pose_x", "max_base_pose_x"))
    init_pole_angle: float = param(0.0, low=-3.2, high=3.2, unit="rad", doc="pole angle at reset")
    init_noise: float = param(0.05, low=0.0, high=1.0, doc="uniform noise on each state variable at reset")
    cart_v_bound: float = param(2.0, low=0.0, low_open=True, unit="m/s", doc="state_bounds range of cart_v")
    pole_vel_bound: float = param(3.0, low=0.0, low_open=True, unit="rad/s", doc="state_bounds range of pole vel")


class CartPoleContinuous(CartPoleStayUp):
    """:class:`envs.cartpole.stay_up.CartPoleStayUp` with a ``Box(-1, 1, (1,))`` action."""

    Options = Options
    Params = Params
    action_dtype = jnp.float32
    #: The discrete ids this task is the continuous counterpart of (named by the Brax adapter's refusal).
    continuous_of: ClassVar[tuple[str, ...]] = ("CartPoleStayUp-v0", "CartPoleStayUpLeftRight-v0")
    learning_target = LearningTarget("over_500", "mean_length", 500.0, "mean greedy episode length >= 500 steps")
    #: None: the discrete task's chunk kernel holds its discrete action map, not this task's.
    chunk_kernel = None
    #: None: the discrete task's host step holds its discrete action map.
    host_step = None

    def __init__(self, options: Options | None = None, params: Params | None = None):
        # CartPoleStayUp.__init__ builds the increments of the discrete actions; only the robot is needed here.
        super(CartPoleStayUp, self).__init__(options, params)
        o = self.options
        self.robot = CartPoleRobot(o.control_type, o.backend, o.running_step, o.timestep)

    def action_space(self, params: Params | None = None) -> spaces.Box:
        one = np.ones(1, np.float32)
        return spaces.Box(-one, one, ("command",))

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> tuple:
        return ()

    def _set_action(self, action: jax.Array, task: tuple, params: Params) -> tuple[jax.Array, tuple]:
        a = jnp.clip(jnp.reshape(action, (-1,))[:1], -1.0, 1.0)
        return (params.max_command * a).astype(jnp.float32), task

    def _get_obs(self, pipeline_state: Any, task: tuple, params: Params) -> jax.Array:
        return self.robot.read_sensors(pipeline_state).astype(jnp.float32)


__all__ = ["CartPoleContinuous", "Options", "Params"]
