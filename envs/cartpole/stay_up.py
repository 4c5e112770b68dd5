"""CartPoleStayUp: keep the pole up by moving the cart (openai_ros' ``CartPoleStayUpEnv``, seed 001).

Environment card
----------------
Actions      ``Discrete(n_actions)``; each adds to the cart command, which the ``control_type`` controller tracks:
             0 left ``-pos_step``, 1 right ``+pos_step``, 2 left big ``-10 pos_step``, 3 right big
             ``+10 pos_step``. ``-v0`` has 4 actions, ``-v1`` (seed exercise 2.3) only left/right.
             A velocity command is clipped to ``±max_base_velocity``.
Observation  ``[cart_x (m), cart_v (m/s), pole_angle (rad), pole_angular_velocity (rad/s)]``; rounded to 0.1
             as the seed did when ``round_obs`` is set.
Reward       1.0 every step, including the step on which the episode terminates.
Termination  ``cart_x <= min_base_pose_x`` or ``cart_x >= max_base_pose_x``, or the pole angle outside
             ``(min_pole_angle, max_pole_angle)``. Truncation at ``max_episode_steps`` (the seed's 1000).
Control      one step holds the command for ``running_step`` s (0.04), i.e. ``running_step / timestep`` physics
             steps.
Reset        cart at ``init_pos`` (m), pole at ``init_pole_angle`` (rad; seed exercise 2.5 asks for 30° =
             0.5236), each of the four state variables plus uniform noise in ``±init_noise``; command 0.
Parameters   see :class:`Options` (static: model and code path) and :class:`Params` (numbers; vmappable).
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from envs.cartpole.host import HostStayUp
from envs.cartpole.kernel import CHUNK_KERNEL
from envs.cartpole.robot import BACKENDS, CONTROL_TYPES, CartPoleRobot
from envs.cartpole.rules import ACTION_STEPS, REWARD, command_after, fell, observation
from jaxrobo.api import (BaseParams, LearningTarget, TaskEnv, param, pytree_dataclass, randomise, range_param, rng,
                         spaces)
OBS_NAMES = ("cart_x", "cart_v", "pole_angle", "pole_angular_velocity")


@pytree_dataclass
class Options:
    n_actions: int = param(4, choices=(2, 4), static=True, doc="4: the seed's v0; 2: left/right only (v1)")
    control_type: str = param("velocity", choices=CONTROL_TYPES, static=True, doc="controller receiving the command")
    backend: str = param("mjx", choices=BACKENDS, static=True,
                         doc="physics: 'mjx', a Brax pipeline, or 'analytic' (same model in closed form, fastest)")
    running_step: float = param(0.04, low=0.0, low_open=True, high=1.0, static=True, unit="s",
                                doc="control period")
    timestep: float = param(0.01, low=0.0, low_open=True, high=0.04, static=True, unit="s", doc="physics step")
    round_obs: bool = param(False, static=True, doc="round observations to 0.1 as the seed did")
    randomise: bool = param(False, static=True,
                            doc="domain randomisation: draw the physics (the rand_* ranges) at every reset; the "
                                "Pallas chunk kernel draws them at its in-kernel resets")


@pytree_dataclass
class Params(BaseParams):
    pos_step: float = param(0.016, low=0.0, low_open=True, high=10.0, doc="command increment per action")
    min_pole_angle: float = param(-0.7, low=-3.2, high=0.0, unit="rad", doc="-40 deg, the seed's limit")
    max_pole_angle: float = param(0.7, low=0.0, high=3.2, unit="rad", doc="+40 deg, the seed's limit")
    min_base_pose_x: float = param(-2.5, low=-100.0, high=0.0, unit="m")
    max_base_pose_x: float = param(2.5, low=0.0, high=100.0, unit="m")
    max_base_velocity: float = param(50.0, low=0.0, low_open=True, unit="m/s", doc="clip of a velocity command")
    init_pos: float = param(0.0, low=-100.0, high=100.0, unit="m", doc="cart position at reset",
                            within=("min_base_pose_x", "max_base_pose_x"))
    init_pole_angle: float = param(0.0, low=-3.2, high=3.2, unit="rad", doc="pole angle at reset")
    init_noise: float = param(0.05, low=0.0, high=1.0, doc="uniform noise on each state variable at reset")
    cart_v_bound: float = param(2.0, low=0.0, low_open=True, unit="m/s", doc="discretiser range of cart_v")
    pole_vel_bound: float = param(3.0, low=0.0, low_open=True, unit="rad/s", doc="discretiser range of pole vel")
    # Domain randomisation (read only with the option randomise=true; docs/randomisation.md).
    rand_cart_mass: tuple = range_param((1.0, 1.0), low=0.25, high=4.0, doc="factor on the cart's mass")
    rand_pole_mass: tuple = range_param((1.0, 1.0), low=0.25, high=4.0, doc="factor on the pole's mass")
    rand_pole_length: tuple = range_param((1.0, 1.0), low=0.5, high=2.0,
                                          doc="factor on the pole's length (centre of mass and inertia, as a rod)")
    rand_obs_noise: tuple = randomise.obs_noise_range()


@pytree_dataclass
class TaskVars:
    """Per-episode variables: the accumulated cart command (the seed's ``self.pos``)."""

    command: jax.Array


class CartPoleStayUp(TaskEnv):
    Options = Options
    Params = Params
    #: Learned: greedy episodes keep the pole up for half of the seed's 1000 steps on average.
    learning_target = LearningTarget("over_500", "mean_length", 500.0, "mean greedy episode length >= 500 steps")
    #: A training chunk of this task with Q-learning as one Pallas kernel (:mod:`envs.cartpole.kernel`), for the runs
    #: its ``unsupported_run`` takes.
    chunk_kernel = CHUNK_KERNEL
    #: One env's step on the host in Python floats (:mod:`envs.cartpole.host`), for ``engine="numpy"``.
    host_step = HostStayUp

    def __init__(self, options: Options | None = None, params: Params | None = None):
        super().__init__(options, params)
        o = self.options
        self.robot = CartPoleRobot(o.control_type, o.backend, o.running_step, o.timestep)
        self._steps = jax.device_put(np.asarray(ACTION_STEPS[: o.n_actions], np.float32))  # on the host: no program
        randomise.check(self)

    # ---- spaces -----------------------------------------------------------------------------------------
    def action_space(self, params: Params | None = None) -> spaces.Discrete:
        return spaces.Discrete(self.options.n_actions)

    def observation_space(self, params: Params | None = None) -> spaces.Box:
        inf = np.full(4, np.inf, np.float32)
        return spaces.Box(-inf, inf, OBS_NAMES)

    def state_bounds(self, params: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self.default_params if params is None else params
        x_lo, v, a_lo, w = (float(b) for b in (p.min_base_pose_x, p.cart_v_bound, p.min_pole_angle, p.pole_vel_bound))
        x_hi, a_hi = float(p.max_base_pose_x), float(p.max_pole_angle)
        return np.array([x_lo, -v, a_lo, -w], np.float32), np.array([x_hi, v, a_hi, w], np.float32)

    # ---- the seed's hooks -------------------------------------------------------------------------------
    def _set_init_pose(self, key: jax.Array, params: Params) -> tuple[jax.Array, jax.Array]:
        noise = rng.uniform(key, (4,), -params.init_noise, params.init_noise)
        return self.robot.init_pose(params.init_pos + noise[0], params.init_pole_angle + noise[2], noise[1], noise[3])

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Params) -> TaskVars:
        start = params.init_pos if self.options.control_type == "position" else 0.0
        return TaskVars(command=jnp.asarray(start, jnp.float32))

    def _set_action(self, action: jax.Array, task: TaskVars, params: Params) -> tuple[jax.Array, TaskVars]:
        velocity = self.options.control_type == "velocity"
        command = command_after(task.command, self._steps[action], params.pos_step,
                                params.max_base_velocity if velocity else None, jnp)
        return command[None], TaskVars(command)

    def _get_obs(self, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        return observation(self.robot.read_sensors(pipeline_state), self.options.round_obs, jnp)

    def _is_done(self, obs: jax.Array, pipeline_state: Any, task: TaskVars, params: Params) -> jax.Array:
        p = params
        return fell(obs[0], obs[2], p.min_base_pose_x, p.max_base_pose_x, p.min_pole_angle, p.max_pole_angle)

    def _compute_reward(self, obs, done, action, pipeline_state, task, params) -> tuple[jax.Array, TaskVars]:
        return jnp.full((), REWARD, jnp.float32), task
