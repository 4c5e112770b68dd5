"""ArmReach in native MuJoCo (``mujoco.MjData``, the C engine, float64, one env): the sim-to-sim check of an
exported policy (``scripts/sim2sim.py``).

The task's step runs the env's own functions over numpy (``envs/arm/reach.py``: :func:`set_points`,
:func:`observation`, :func:`reached`; the fingertip of ``envs/arm/robot.py``), in float64: the action moves one
servo set-point by ``joint_step`` (the elbow's clamped to ``[0, ELBOW_MAX]``), the set-points are the position
actuators' controls for ``running_step / timestep`` ``mj_step`` calls, the observation is the elbow angle and the
goal relative to the fingertip in the upper arm's frame (float32), and the episode ends when the fingertip is
within ``goal_tolerance`` (success) or at ``max_episode_steps``. Every number comes from the task object the run
built and its compiled model; nothing here calls JAX.
"""
from __future__ import annotations

from typing import Any, Callable

import numpy as np

from envs.arm.reach import ACTION_DELTAS, observation, reached, set_points
from jaxrobo.api import NativeSim


class NativeArm(NativeSim):
    """One ArmReach in native MuJoCo with the task's action mapping, observation and success test."""

    def __init__(self, env: Any, params: Any = None):
        p = env.default_params if params is None else params
        r = env.robot
        super().__init__(r.sim)
        self.deltas = np.asarray(ACTION_DELTAS, np.float64)
        self.joint_step = float(p.joint_step)
        self.tolerance = float(p.goal_tolerance)
        self.horizon = int(p.max_episode_steps)
        self.q_idx = list(r.q)

    def observe(self, goal: np.ndarray) -> np.ndarray:
        return observation(self.data.qpos[self.q_idx], goal, np)

    def episode(self, policy: Callable[[np.ndarray], int], qpos: np.ndarray, qvel: np.ndarray, task: Any,
                horizon: int | None = None) -> dict[str, Any]:
        """One episode from ``(qpos, qvel)`` with the task's set-points (``task.command``) and ``task.goal``:
        ``length``, ``success`` (reached), ``actions`` and ``obs``."""
        horizon = self.horizon if horizon is None else int(horizon)
        self.reset(qpos, qvel)
        command = np.asarray(task.command, np.float64).copy()
        goal = np.asarray(task.goal, np.float64)
        obs = self.observe(goal)
        seen, actions, done = [obs], [], False
        for _ in range(horizon):
            a = int(policy(obs))
            command = set_points(command, self.deltas[a], self.joint_step, np)
            self.advance(command)
            obs = self.observe(goal)
            actions.append(a)
            seen.append(obs)
            done = bool(reached(obs, self.tolerance, np))
            if done:
                break
        return {"length": len(actions), "success": done, "actions": np.asarray(actions, np.int32),
                "obs": np.asarray(seen)}
