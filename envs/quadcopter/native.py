"""QuadcopterGoto-v1/-v2 and QuadcopterGotoTwist-v0 in native MuJoCo (``mujoco.MjData``, the C engine, float64, one
env): the sim-to-sim check of an exported policy (``scripts/sim2sim.py``) and the ROS sim node's robot.

Nothing of the task is ported here. The on-board cascade run before every ``mj_step`` is
:func:`envs.quadcopter.dynamics.controller`; the level sonars, the outcome (arrival, crash into the ground or an
obstacle, leaving the workspace, altitude and inclination limits) and the reward are
:mod:`envs.quadcopter.goto_step`'s (on :mod:`envs.quadcopter.geometry`): the functions the JAX task's hooks and its
Pallas kernel run, called here on float64 scalars (``xp = numpy``; the controller, 30 times a control step, on
Python floats: :data:`jaxrobo.core.scalar.FLOATS`). The observation and the command are
:class:`jaxrobo.interop.numpy_policy.QuadcopterIO`'s, the robot side an export carries (``policy.json``'s ``robot``,
:meth:`NativeGoto.robot_section`): the port and an exported policy compute them with the same code. Every constant
is read from the task object the run built (its options, params and robot: mass, inertia, mixing, gains, all
derived from the MJCF) and the model is the robot's own compiled ``MjModel``; nothing here imports JAX
(``tests/test_structure.py`` checks it).
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from envs.quadcopter import goto_step
from envs.quadcopter.dynamics import controller
from envs.quadcopter.geometry import euler
from jaxrobo.api import scalar
from jaxrobo.interop.numpy_policy import QuadcopterIO
from jaxrobo.interop.native import NativeSim


class NativeGoto(NativeSim):
    """One QuadcopterGoto (v1 or v2: v2 when its observation has ``goal_clear``; GotoTwist when its action is a
    Box) in native MuJoCo."""

    def __init__(self, env: Any, params: Any = None):
        p = env.default_params if params is None else params
        r = env.robot
        super().__init__(r.sim)
        self.v2 = "goal_clear" in env.observation_space().names
        self.p = {k: float(getattr(p, k)) for k in (goto_step.V2_PARAMS if self.v2 else goto_step.V1_PARAMS)}
        self.horizon = int(p.max_episode_steps)
        self.kinds = goto_step.kinds_of(env.options.obstacle_kind)
        self.continuous = hasattr(env.action_space(), "low")  # GotoTwist: the action is the Twist
        c = {"family": "quadcopter", "period": float(self.n_substeps * self.model.opt.timestep),
             "continuous": self.continuous, "v2": self.v2, "speed_value": self.p["speed_value"],
             "sonar_range": self.p["sonar_range"]}
        if self.v2:
            c.update({k: self.p[k] for k in ("dz_lead", "drone_radius", "clear_margin")})
        if not self.continuous:
            c["actions"] = [[float(x) for x in goto_step.twist(np, a, self.p["speed_value"])]
                            for a in range(len(goto_step.ACTION_NAMES))]
        self.constants = c
        self.io = QuadcopterIO(c)
        self.control = r.control  # the controller's constants (envs.quadcopter.dynamics.ControllerConstants)

    # ---- robot ------------------------------------------------------------------------------------------
    def controller(self, command: np.ndarray) -> np.ndarray:
        """Twist -> rotor thrusts (N): :func:`envs.quadcopter.dynamics.controller` on float64 scalars."""
        q, v = self.data.qpos.tolist(), self.data.qvel.tolist()
        return np.array(controller(scalar.FLOATS, self.control, q, v, [float(x) for x in command]), np.float64)

    # ---- task -------------------------------------------------------------------------------------------
    def _observe(self, goal: np.ndarray, obstacles: dict) -> tuple:
        """:func:`envs.quadcopter.goto_step.observe` of the drone as it is: ``(obs, goal distance, nearest
        obstacle surface)``."""
        q = self.data.qpos
        yaw = euler(np, *q[3:7])[2]
        return goto_step.observe(np, list(q[:3]), yaw, self.data.qvel[2], list(np.asarray(goal, np.float64)), self.p,
                                 self.v2, self.kinds, goto_step.loop_fold(np, obstacles))

    def sonars(self, obstacles: dict) -> list[float]:
        """The four level sonars (forward, left, right, down; m): rays against the ground and the obstacles."""
        return [float(x) for x in self._observe(self.data.qpos[:3], obstacles)[0][3:7]]

    def observation(self, pos: np.ndarray, quat: np.ndarray, vz: float, sonars, goal: np.ndarray,
                    obstacles: dict) -> np.ndarray:
        """The task's observation from the drone's readings: position (m), orientation quaternion ``(w, x, y, z)``,
        vertical velocity (m/s), the four sonars (m), and the goal and obstacles."""
        return self.io.observation(pos, quat, vz, sonars, goal, obstacles)

    def observe(self, goal: np.ndarray, obstacles: dict) -> np.ndarray:
        q = self.data.qpos
        return self.observation(q[:3], q[3:7], self.data.qvel[2], self.sonars(obstacles), goal, obstacles)

    def command(self, action: Any) -> tuple[Any, np.ndarray]:
        """``(action as recorded, Twist [vx, vy, vz, yaw_rate])`` of a policy's action (heading frame, m/s, rad/s):
        a discrete action's seed Twist at ``speed_value``, or GotoTwist's ``speed_value * clip(a, -1, 1)``."""
        return self.io.command(action)

    def robot_section(self) -> dict:
        """``policy.json``'s ``robot``: what a policy driving the drone needs of the task (plain JSON)."""
        return dict(self.constants)

    def outcome(self, goal: np.ndarray, obstacles: dict) -> tuple[bool, bool]:
        q = self.data.qpos
        _, dist, point = self._observe(goal, obstacles)
        roll, pitch, _ = euler(np, *q[3:7])
        arrived, failed = goto_step.outcome(np, list(q[:3]), roll, pitch, dist, point, self.p)
        return bool(arrived), bool(failed)

    def reward(self, obs: np.ndarray, prev: dict, arrived: bool, failed: bool) -> tuple[float, dict]:
        """The task's reward of the step that led to ``obs`` (its float32 observation; the drone where the step
        left it): :func:`envs.quadcopter.goto_step.reward`, and the potentials it leaves for the next step.
        ``prev``: ``dist`` (and v2's ``bearing``, ``dz``), the task variables ``prev_dist`` (``prev_bearing``,
        ``prev_dz``): at an episode's start, its reset's."""
        task = {"prev_dist": prev["dist"], "arrived": False, "crashed": False}
        if self.v2:
            task.update(prev_bearing=prev["bearing"], prev_dz=prev["dz"])
        values = [float(x) for x in obs[:3]]
        reward, nxt = goto_step.reward(np, self.p, task, values, values[0], self.data.qpos[2], arrived, failed, self.v2)
        out = {"dist": nxt["prev_dist"]}
        if self.v2:
            out.update(bearing=nxt["prev_bearing"], dz=nxt["prev_dz"])
        return float(reward), out

    def potentials(self, task: Any) -> dict:
        """The reward's potentials at an episode's start: its reset's task variables (``prev_*``)."""
        out = {"dist": float(np.asarray(task.prev_dist))}
        if self.v2:
            out.update(bearing=float(np.asarray(task.prev_bearing)), dz=float(np.asarray(task.prev_dz)))
        return out

    def potentials_of(self, obs: np.ndarray) -> dict:
        """The potentials a state observed as ``obs`` (float32) holds, as :meth:`reward` passes them on: the goal
        distance (v2: ``|goal_bearing|``, ``|goal_dz|``). At an episode's first state they are its reset's task
        variables (the drone at rest: goal_dz's lead adds nothing), to float32 round-off: how a client that sees
        the readings only (``jaxrobo.ros``'s Gymnasium env) starts the reward."""
        out = {"dist": float(obs[0])}
        if self.v2:
            out.update(bearing=abs(float(obs[1])), dz=abs(float(obs[2])))
        return out

    def episode(self, policy: Callable[[np.ndarray], int], qpos: np.ndarray, qvel: np.ndarray, task: Any,
                horizon: int | None = None) -> dict[str, Any]:
        """One flight from ``(qpos, qvel)`` to the goal among the obstacles of ``task`` (one episode's task
        variables as host arrays: ``goal``, ``obstacles.kind/center/size/active``): ``length``, ``success``
        (arrived), ``crashed``, ``return`` (the task's reward summed), ``actions``, ``obs`` and ``pos`` per step."""
        horizon = self.horizon if horizon is None else int(horizon)
        goal = np.asarray(task.goal, np.float64)
        o = task.obstacles
        obstacles = {"kind": np.asarray(o.kind), "center": np.asarray(o.center, np.float64),
                     "size": np.asarray(o.size, np.float64), "active": np.asarray(o.active)}
        self.reset(qpos, qvel)
        obs = self.observe(goal, obstacles)
        seen, actions, pos = [obs], [], [self.data.qpos[:3].copy()]
        arrived = failed = False
        prev, ret = self.potentials(task), 0.0
        for _ in range(horizon):
            a, command = self.command(policy(obs))
            self.advance(lambda: self.controller(command))  # the cascade runs on the state before every mj_step
            obs = self.observe(goal, obstacles)
            actions.append(a)
            seen.append(obs)
            pos.append(self.data.qpos[:3].copy())
            arrived, failed = self.outcome(goal, obstacles)
            r, prev = self.reward(obs, prev, arrived, failed)
            ret += r
            if arrived or failed:
                break
        return {"length": len(actions), "success": arrived, "crashed": failed, "return": ret,
                "actions": np.asarray(actions, np.float32 if self.continuous else np.int32), "obs": np.asarray(seen),
                "pos": np.asarray(pos)}
