"""ArmReach in native MuJoCo (``mujoco.MjData``, the C engine, float64, one env): the sim-to-sim check of an
exported policy (``scripts/sim2sim.py``).

The task's step, ported to numpy: the action moves one servo set-point by ``joint_step`` (the elbow's clamped to
``[0, ELBOW_MAX]``), the set-points are the position actuators' controls for ``running_step / timestep`` ``mj_step``
calls, the observation is the elbow angle and the goal relative to the fingertip in the upper arm's frame (float32),
and the episode ends when the fingertip is within ``goal_tolerance`` (success) or at ``max_episode_steps``. Every
number comes from the task object the run built and its compiled model; nothing here calls JAX.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from envs.arm.reach import ACTION_DELTAS
from envs.arm.robot import ELBOW_MAX, FORE, UPPER
from jaxrobo.api import NativeSim


def fingertip(q: np.ndarray) -> np.ndarray:
    a = q[0] + q[1]
    return np.array([UPPER * math.cos(q[0]) + FORE * math.cos(a), UPPER * math.sin(q[0]) + FORE * math.sin(a)])


class NativeArm(NativeSim):
    """One ArmReach in native MuJoCo with the task's action mapping, observation and success test."""

    def __init__(self, env: Any, params: Any = None):
        p = env.default_params if params is None else params
        r = env.robot
        super().__init__(r.sim)
        self.deltas = np.asarray(ACTION_DELTAS, np.float64) * float(p.joint_step)
        self.tolerance = float(p.goal_tolerance)
        self.horizon = int(p.max_episode_steps)
        self.q_idx = list(r.q)

    def observe(self, goal: np.ndarray) -> np.ndarray:
        q = self.data.qpos[self.q_idx]
        d = goal - fingertip(q)
        c, s = math.cos(q[0]), math.sin(q[0])
        return np.array([q[1], c * d[0] + s * d[1], -s * d[0] + c * d[1]]).astype(np.float32)

    def episode(self, policy: Callable[[np.ndarray], int], qpos: np.ndarray, qvel: np.ndarray, task: Any,
                horizon: int | None = None) -> dict[str, Any]:
        """One episode from ``(qpos, qvel)`` with the task's set-points (``task.command``) and ``task.goal``:
        ``length``, ``success`` (reached), ``actions`` and ``obs``."""
        horizon = self.horizon if horizon is None else int(horizon)
        self.reset(qpos, qvel)
        command = np.asarray(task.command, np.float64).copy()
        goal = np.asarray(task.goal, np.float64)
        obs = self.observe(goal)
        seen, actions, reached = [obs], [], False
        for _ in range(horizon):
            a = int(policy(obs))
            command = command + self.deltas[a]
            command[1] = min(max(command[1], 0.0), ELBOW_MAX)
            self.advance(command)
            obs = self.observe(goal)
            actions.append(a)
            seen.append(obs)
            reached = bool(np.linalg.norm(obs[1:]) < self.tolerance)
            if reached:
                break
        return {"length": len(actions), "success": reached, "actions": np.asarray(actions, np.int32),
                "obs": np.asarray(seen)}
