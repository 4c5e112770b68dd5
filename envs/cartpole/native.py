"""CartPoleStayUp and CartPoleContinuous in native MuJoCo (``mujoco.MjData``, the C engine, float64, one env): the
sim-to-sim check of an exported policy (``scripts/sim2sim.py``).

The task's step, ported to numpy: a discrete action adds ``ACTION_STEPS[a] * pos_step`` to the cart command (clipped to
``±max_base_velocity`` under velocity control), a continuous one (CartPoleContinuous, ``Box(-1, 1)``) is the command
``max_command * clip(a, -1, 1)`` itself; the command is the actuator's control for ``running_step / timestep``
``mj_step`` calls, the observation is the joint sensors cast to float32 (rounded to 0.1 with ``round_obs``), the episode
terminates when the cart or the pole leaves its limits and is cut at ``max_episode_steps``. Success: the pole stayed up
for the whole horizon. Every number comes from the task object the run built (its options and params) and its compiled
model; nothing here calls JAX. The observation and the command are :class:`jaxrobo.api.numpy_policy.CartPoleIO`'s, the
robot side an export carries (``policy.json``'s ``robot``, :meth:`NativeCartPole.robot_section`): the port and an
exported policy compute them with the same code.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from envs.cartpole.rules import ACTION_STEPS
from jaxrobo.api import NativeSim, numpy_policy


class NativeCartPole(NativeSim):
    """One cart-pole in native MuJoCo with the task's action mapping, observation and termination."""

    def __init__(self, env: Any, params: Any = None, start_command: float = 0.0):
        """``start_command``: the cart command an episode starts from (the discrete task's reset draws it; what
        :meth:`robot_section` records for a policy driving a robot)."""
        p = env.default_params if params is None else params
        o = env.options
        super().__init__(env.robot.sim)
        continuous = hasattr(env.action_space(), "low")  # a Box: the action is the command
        c = {"family": "cartpole", "period": float(self.n_substeps * self.model.opt.timestep),
             "continuous": continuous, "round_obs": bool(getattr(o, "round_obs", False)),
             "start_command": float(start_command)}
        if continuous:
            c["max_command"] = float(p.max_command)
        else:
            c.update(steps=list(ACTION_STEPS[: o.n_actions]), pos_step=float(p.pos_step),
                     velocity=o.control_type == "velocity", vmax=float(p.max_base_velocity))
        self.constants = c
        self.io = numpy_policy.CartPoleIO(c)
        self.continuous = continuous
        self.x_lim = (float(p.min_base_pose_x), float(p.max_base_pose_x))
        self.angle_lim = (float(p.min_pole_angle), float(p.max_pole_angle))
        self.horizon = int(p.max_episode_steps)
        r = env.robot
        self.idx = (r.cart_q, r.cart_v, r.pole_q, r.pole_v)

    def robot_section(self) -> dict:
        """``policy.json``'s ``robot``: what a policy driving the cart-pole needs of the task (plain JSON)."""
        return dict(self.constants)

    def joints(self) -> np.ndarray:
        """``[cart_x, cart_v, pole_angle, pole_angular_velocity]`` (float64): the joint sensors."""
        q, v = self.data.qpos, self.data.qvel
        c_q, c_v, p_q, p_v = self.idx
        return np.array([q[c_q], v[c_v], q[p_q], v[p_v]])

    def observation(self, joints) -> np.ndarray:
        """The task's observation from the joint readings (what the ROS policy node builds from JointState)."""
        return self.io.observation(joints)

    def observe(self) -> np.ndarray:
        return self.observation(self.joints())

    def command(self, action: Any, command: float) -> tuple[Any, float]:
        """``(action as recorded, new cart command)``: a discrete action adds its step to the last ``command``
        (clipped under velocity control); a continuous one is ``max_command * clip(a, -1, 1)``."""
        return self.io.command(action, command)

    def terminated(self, obs: np.ndarray) -> bool:
        """The cart or the pole out of its limits (on the observation, as the task tests it)."""
        x, angle = obs[0], obs[2]
        return bool(x <= self.x_lim[0] or x >= self.x_lim[1] or angle <= self.angle_lim[0]
                    or angle >= self.angle_lim[1])

    def episode(self, policy: Callable[[np.ndarray], int], qpos: np.ndarray, qvel: np.ndarray, task: Any,
                horizon: int | None = None) -> dict[str, Any]:
        """One episode from ``(qpos, qvel)`` and, for the discrete task, its start command (``task.command``):
        ``length``, ``terminated``, ``success`` (up for the horizon), ``actions`` and ``obs`` (the observations
        the policy saw)."""
        horizon = self.horizon if horizon is None else int(horizon)
        self.reset(qpos, qvel)
        command = 0.0 if self.continuous else float(task.command)
        obs = self.observe()
        seen, actions, terminated = [obs], [], False
        for _ in range(horizon):
            a, command = self.command(policy(obs), command)
            self.advance(command)  # the model keeps one actuator: the control type's
            obs = self.observe()
            actions.append(a)
            seen.append(obs)
            terminated = self.terminated(obs)
            if terminated:
                break
        length = len(actions)
        return {"length": length, "terminated": terminated, "success": length == horizon and not terminated,
                "actions": np.asarray(actions, np.float32 if self.continuous else np.int32), "obs": np.asarray(seen)}
