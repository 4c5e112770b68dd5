"""QuadcopterGoto-v1/-v2 and QuadcopterGotoTwist-v0 in native MuJoCo (``mujoco.MjData``, the C engine, float64, one env): the sim-to-sim check
of an exported policy (``scripts/sim2sim.py``).

Ported to numpy from :mod:`envs.quadcopter.robot`, :mod:`envs.quadcopter.goto` and :mod:`envs.quadcopter.goto_v2`:
the Twist of each action (GotoTwist: ``speed_value * clip(a, -1, 1)`` of its ``Box(-1, 1, (4,))`` action), the
on-board cascade (velocity -> tilt/thrust -> attitude PD -> rotor thrusts through the
inverse mixing matrix, clipped to the motor limits) run before every ``mj_step``, the level sonars and v2's
``goal_clear`` (exact ray tests against the ground and the episode's obstacles), and the outcome (arrival, crash
into the ground or an obstacle, leaving the workspace, altitude and inclination limits). Every constant is read
from the task object the run built (its options, params and robot: mass, inertia, mixing, gains, all derived from
the MJCF) and the model is the robot's own compiled ``MjModel``; nothing here calls JAX. The observation and the
command are :class:`jaxrobo.api.numpy_policy.QuadcopterIO`'s, the robot side an export carries (``policy.json``'s
``robot``, :meth:`NativeGoto.robot_section`): the port and an exported policy compute them with the same code.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from envs.quadcopter.robot import _ACTION_FIXED, _ACTION_SCALE, _INF, _PARALLEL, BOX, SONAR_RAYS
from jaxrobo.api import NativeSim, numpy_policy


def point_obstacle_distance(p, obstacles: dict) -> float:
    d = _INF
    for kind, center, size, active in zip(obstacles["kind"], obstacles["center"], obstacles["size"],
                                          obstacles["active"]):
        if not active:
            continue
        q = np.abs(p - center)
        if kind == BOX:
            d = min(d, math.sqrt(np.sum(np.maximum(q - size, 0.0) ** 2)))
        else:
            radial = max(math.hypot(q[0], q[1]) - size[0], 0.0)
            d = min(d, math.hypot(radial, max(q[2] - size[2], 0.0)))
    return d


class NativeGoto(NativeSim):
    """One QuadcopterGoto (v1 or v2: v2 when its observation has ``goal_clear``; GotoTwist when its action is a
    Box) in native MuJoCo."""

    def __init__(self, env: Any, params: Any = None):
        p = env.default_params if params is None else params
        r = env.robot
        super().__init__(r.sim)
        self.p = {k: float(getattr(p, k)) for k in (
            "speed_value", "goal_tolerance", "workspace", "max_altitude", "max_incl", "drone_radius", "sonar_range")}
        self.horizon = int(p.max_episode_steps)
        names = ("progress_reward", "step_cost", "altitude_cost", "arrival_bonus", "crash_penalty")
        self.r = {k: float(getattr(p, k)) for k in names + (("heading_reward", "climb_reward") if
                                                             "goal_clear" in env.observation_space().names else ())}
        self.v2 = "goal_clear" in env.observation_space().names
        self.continuous = hasattr(env.action_space(), "low")  # GotoTwist: the action is the Twist
        c = {"family": "quadcopter", "period": float(self.n_substeps * self.model.opt.timestep),
             "continuous": self.continuous, "v2": self.v2, "speed_value": self.p["speed_value"],
             "sonar_range": self.p["sonar_range"], "box_kind": int(BOX), "parallel": float(_PARALLEL),
             "inf": float(_INF)}
        if self.v2:
            c.update(dz_lead=float(getattr(p, "dz_lead", 0.0)), grow=float(p.drone_radius) + float(p.clear_margin))
        if not self.continuous:
            c["actions"] = (_ACTION_SCALE.astype(np.float64) * self.p["speed_value"] + _ACTION_FIXED).tolist()
        self.constants = c
        self.io = numpy_policy.QuadcopterIO(c)
        c = r.control  # the controller's constants (envs.quadcopter.dynamics.ControllerConstants)
        self.gains, self.g, self.mass = r.gains, float(c.g), float(c.mass)
        self.inertia = np.asarray(c.inertia, np.float64)
        self.unmix = np.asarray(c.unmix, np.float64)
        self.ctrl_low, self.ctrl_high = np.asarray(c.ctrl_low, np.float64), np.asarray(c.ctrl_high, np.float64)
        self.min_altitude = float(r.min_altitude)

    # ---- robot ------------------------------------------------------------------------------------------
    def controller(self, command: np.ndarray) -> np.ndarray:
        """Twist -> rotor thrusts (N): :meth:`envs.quadcopter.robot.Quadcopter.controller` in float64."""
        k, g = self.gains, self.g
        q, v = self.data.qpos, self.data.qvel
        roll, pitch, yaw = numpy_policy.euler_from_quat(q[3:7])
        omega = v[3:6]
        vz_cmd = command[2]
        if self.min_altitude > 0:
            vz_cmd = max(vz_cmd, k.k_floor * (self.min_altitude - q[2]))
        c, s = math.cos(yaw), math.sin(yaw)
        vx_h, vy_h = c * v[0] + s * v[1], -s * v[0] + c * v[1]
        a_max = g * math.tan(k.max_tilt)
        clip = lambda x, lo, hi: min(max(x, lo), hi)  # noqa: E731
        ax = clip(k.k_vel_xy * (command[0] - vx_h), -a_max, a_max)
        ay = clip(k.k_vel_xy * (command[1] - vy_h), -a_max, a_max)
        az = clip(k.k_vel_z * (vz_cmd - v[2]), -k.max_acc_down, k.max_acc_up)
        pitch_d = clip(math.atan2(ax, g + az), -k.max_tilt, k.max_tilt)
        roll_d = clip(math.atan2(-ay, g + az), -k.max_tilt, k.max_tilt)
        thrust = self.mass * (g + az) / max(math.cos(roll) * math.cos(pitch), 0.5)
        torque = self.inertia * np.array([k.k_att * (roll_d - roll) - k.k_rate * omega[0],
                                          k.k_att * (pitch_d - pitch) - k.k_rate * omega[1],
                                          k.k_yaw * (command[3] - omega[2])])
        return np.clip(self.unmix @ np.concatenate([[thrust], torque]), self.ctrl_low, self.ctrl_high)

    # ---- task -------------------------------------------------------------------------------------------
    def ray_ground(self, origin: np.ndarray, direction: np.ndarray) -> float:
        t = -origin[2] * float(self.io.safe_inv(direction[2]))
        if direction[2] < -_PARALLEL or origin[2] <= 0:
            return max(t, 0.0) * float(origin[2] > 0)
        return _INF

    def sonars(self, obstacles: dict) -> list[float]:
        """The four level sonars (forward, left, right, down; m): rays against the ground and the obstacles."""
        pos, yaw = self.data.qpos[:3], numpy_policy.euler_from_quat(self.data.qpos[3:7])[2]
        c, s = math.cos(yaw), math.sin(yaw)
        level = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # heading only: gimballed sonars
        rng = self.p["sonar_range"]
        return [min(self.ray_ground(pos, d), self.io.ray_obstacles(pos, d, obstacles), rng)
                for d in SONAR_RAYS.astype(np.float64) @ level.T]

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
        p = self.p
        pos, rpy = self.data.qpos[:3], numpy_policy.euler_from_quat(self.data.qpos[3:7])
        failed = (pos[2] <= p["drone_radius"] or point_obstacle_distance(pos, obstacles) <= p["drone_radius"]
                  or abs(pos[0]) > p["workspace"] or abs(pos[1]) > p["workspace"] or pos[2] > p["max_altitude"]
                  or abs(rpy[0]) >= p["max_incl"] or abs(rpy[1]) >= p["max_incl"])
        arrived = bool(np.linalg.norm(goal - pos) < p["goal_tolerance"]) and not failed
        return arrived, bool(failed)

    def reward(self, obs: np.ndarray, prev: dict, arrived: bool, failed: bool) -> tuple[float, dict]:
        """The task's reward of the step that led to ``obs`` (its float32 observation; the drone where the step
        left it), as :meth:`envs.quadcopter.goto.QuadcopterGoto._compute_reward` (and v2's shaping) computes it,
        and the potentials it leaves for the next step. ``prev``: ``dist`` (and v2's ``bearing``, ``dz``), the
        task variables ``prev_dist`` (``prev_bearing``, ``prev_dz``): at an episode's start, its reset's."""
        r = self.r
        dist = float(obs[0])
        reward = (r["progress_reward"] * (prev["dist"] - dist) - r["step_cost"] - r["altitude_cost"] * self.data.qpos[2]
                  + (r["arrival_bonus"] if arrived else 0.0) - (r["crash_penalty"] if failed else 0.0))
        nxt = {"dist": dist}
        if self.v2:
            bearing, dz = abs(float(obs[1])), abs(float(obs[2]))
            reward += r["heading_reward"] * (prev["bearing"] - bearing) + r["climb_reward"] * (prev["dz"] - dz)
            nxt.update(bearing=bearing, dz=dz)
        return float(reward), nxt

    def potentials(self, task: Any) -> dict:
        """The reward's potentials at an episode's start: its reset's task variables (``prev_*``)."""
        out = {"dist": float(np.asarray(task.prev_dist))}
        if self.v2:
            out.update(bearing=float(np.asarray(task.prev_bearing)), dz=float(np.asarray(task.prev_dz)))
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
