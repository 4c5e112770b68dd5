"""CartPoleStayUp's step on the host, one env at a time, with no JAX call: what ``gymnasium.make(
"jaxrobo/CartPoleStayUp-v0", engine="numpy")`` steps (:class:`jaxrobo.interop.gym_adapter.JaxroboEnv`).

The task's rules are :mod:`envs.cartpole.rules`' functions (the action map, the observation, the outcome, the
reward), the same the task's hooks and the chunk kernel call; the physics is the backend's own model on the host:

* ``analytic``: :meth:`envs.cartpole.dynamics.CartPoleSim.coordinate_step`, the closed form the JAX path runs,
  on Python floats (:data:`jaxrobo.core.scalar.FLOATS`), its control step's substeps written out once as plain
  arithmetic (:func:`jaxrobo.core.scalar.straight_line`: the same operations, without the calls);
* ``mjx``: native MuJoCo (:class:`jaxrobo.interop.native.NativeSim`, the C engine MJX reimplements) on the robot's
  own compiled model.

Precision, seeds and what is refused: :mod:`jaxrobo.task.host`.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from envs.cartpole.rules import ACTION_STEPS, REWARD, command_after, fell, observation
from jaxrobo.api import HostStep, NativeSim, scalar


class HostStayUp(HostStep):
    """One CartPoleStayUp env on the host. :meth:`set_params` takes the task parameters, :meth:`start` the first
    state of an episode (the JAX reset's, on the host), :meth:`step` steps it; none needs JAX."""

    backends = ("analytic", "mjx")

    def __init__(self, env: Any):
        super().__init__(env)
        o, r = env.options, env.robot
        self.velocity = o.control_type == "velocity"
        self.round_obs = bool(o.round_obs)
        self.steps_of = ACTION_STEPS[: o.n_actions]
        self.n_substeps = int(r.sim.n_substeps)
        self.idx = (r.cart_q, r.cart_v, r.pole_q, r.pole_v)
        if r.sim.backend == "analytic":
            self.sim, self.native = r.sim, None
            self.advance = self._closed_form()
        else:
            self.sim, self.native = None, NativeSim(r.sim)
        self.limits: tuple[float, ...] = ()
        self.coords = (0.0, 0.0, 0.0, 0.0)  # x, θ, ẋ, θ̇ (the closed form's state)
        self.command = 0.0
        self.steps = 0
        self.max_steps = 0
        self.obs = np.zeros(4, np.float32)

    def _closed_form(self) -> Any:
        """``(x, θ, ẋ, θ̇, command) -> (x, θ, ẋ, θ̇)``: one control step of the closed form, written out."""
        sim, n = self.sim, self.n_substeps

        def control_step(xp, x, th, xd, thd, command):
            for _ in range(n):
                x, th, xd, thd = sim.coordinate_step(x, th, xd, thd, (command,), xp=xp)
            return x, th, xd, thd

        return scalar.straight_line(control_step, ("x", "th", "xd", "thd", "command"))

    def set_params(self, params: Any) -> None:
        """The task parameters of the episodes that follow, read as the float32 values the JAX step compares
        with."""
        p = params
        self.pos_step = float(np.float32(p.pos_step))
        self.max_velocity = float(np.float32(p.max_base_velocity)) if self.velocity else None
        self.limits = tuple(float(np.float32(v)) for v in (p.min_base_pose_x, p.max_base_pose_x,
                                                            p.min_pole_angle, p.max_pole_angle))
        self.max_steps = int(p.max_episode_steps)

    def start(self, states: Any, i: int) -> np.ndarray:
        """Begin an episode from the ``i``-th of ``states`` (first states of the task's reset,
        :class:`~jaxrobo.task.env.EnvState` of host arrays with a leading episode axis, the physics state as
        joint coordinates); its observation."""
        qpos = states.pipeline_state.qpos[i].astype(np.float64)
        qvel = states.pipeline_state.qvel[i].astype(np.float64)
        c_q, c_v, p_q, p_v = self.idx
        self.coords = (float(qpos[c_q]), float(qpos[p_q]), float(qvel[c_v]), float(qvel[p_v]))
        if self.native is not None:
            self.native.reset(qpos, qvel)
        self.command = float(states.task.command[i])
        self.steps = int(states.steps[i])
        self.obs = states.obs[i].astype(np.float32)
        return self.obs.copy()

    def sensors(self) -> list[float]:
        """``[cart_x, cart_v, pole_angle, pole_angular_velocity]`` of the current state."""
        if self.native is None:
            x, th, xd, thd = self.coords
            return [x, xd, th, thd]
        q, v = self.native.data.qpos, self.native.data.qvel
        c_q, c_v, p_q, p_v = self.idx
        return [float(q[c_q]), float(v[c_v]), float(q[p_q]), float(v[p_v])]

    def joints(self) -> tuple[np.ndarray, np.ndarray]:
        """``(qpos, qvel)`` of the current state (float64), e.g. to draw it."""
        if self.native is not None:
            return self.native.data.qpos.copy(), self.native.data.qvel.copy()
        x, th, xd, thd = self.coords
        qpos, qvel = np.zeros(2), np.zeros(2)
        c_q, c_v, p_q, p_v = self.idx
        qpos[c_q], qpos[p_q], qvel[c_v], qvel[p_v] = x, th, xd, thd
        return qpos, qvel

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, bool, int]:
        """One step with a checked action index: ``(obs float32[4], reward, terminated, truncated, physics_nan,
        steps)``, as the task's ``step`` gives them."""
        command = command_after(self.command, self.steps_of[action], self.pos_step, self.max_velocity,
                                scalar.FLOATS)
        if self.native is None:
            x, th, xd, thd = self.coords = self.advance(*self.coords, command)
            sensors = [x, xd, th, thd]
        else:
            self.native.advance(command)
            sensors = self.sensors()
        self.steps += 1
        obs = observation(np.array(sensors), self.round_obs, np)
        values = obs.tolist()
        # A non-finite physics state ends the episode with zero reward and the last finite observation and command,
        # as the task's step does. The observation holds every coordinate, so its float32 values are all finite
        # exactly when the state is and fits in float32, the task's test; their sum (float64: no overflow) is
        # finite exactly when they all are.
        if not math.isfinite(sum(values)):
            return self.obs.copy(), 0.0, True, False, True, self.steps
        cart_x, _, angle, _ = values
        terminated = fell(cart_x, angle, *self.limits)  # Python bools
        self.command, self.obs = command, obs
        return obs, REWARD, terminated, self.steps >= self.max_steps and not terminated, False, self.steps
