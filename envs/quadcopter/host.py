"""The Goto tasks' step on the host, one env at a time, with no JAX call: what ``gymnasium.make(
"jaxrobo/QuadcopterGoto-v2", engine="numpy")`` steps (:class:`jaxrobo.interop.gym_adapter.JaxroboEnv`).

Nothing of the task is written here. The action map, the observation, the outcome and the reward are
:mod:`envs.quadcopter.goto_step`'s (on :mod:`envs.quadcopter.geometry`), the on-board cascade is
:func:`envs.quadcopter.dynamics.controller`: the functions the task's hooks, its Pallas kernel and the native port
(:mod:`envs.quadcopter.native`) run, here on Python floats (:data:`jaxrobo.core.scalar.FLOATS`). The
physics is the backend's own on the host:

* ``rigid``: :func:`envs.quadcopter.dynamics.physics_step`, the closed form the JAX path runs, on Python floats,
  its control step's substeps (controller and physics) written out once as plain arithmetic
  (:func:`jaxrobo.core.scalar.straight_line`: the same operations, without the calls);
* ``mjx``: native MuJoCo (:class:`jaxrobo.interop.native.NativeSim`, the C engine MJX reimplements) on the
  robot's own compiled model, as the native port flies it.

Precision, seeds and what is refused: :mod:`jaxrobo.task.host`; float32 round-off accumulates here over a control
step's 30 substeps. The reward's potentials read the float32 observation, as the task's hooks do.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from envs.quadcopter import goto_step
from envs.quadcopter.dynamics import body_constants, controller, physics_step
from envs.quadcopter.geometry import euler
from jaxrobo.api import HostStep, NativeSim, scalar

F = scalar.FLOATS


class HostGoto(HostStep):
    """One QuadcopterGoto (v1 or v2) env on the host. :meth:`set_params` takes the task parameters, :meth:`start`
    the first state of an episode (the JAX reset's, on the host), :meth:`step` steps it; none needs JAX."""

    backends = ("rigid", "mjx")

    def __init__(self, env: Any):
        super().__init__(env)
        r = env.robot
        self.v2 = bool(env.v2)
        self.kinds = goto_step.kinds_of(env.options.obstacle_kind)
        self.control = r.control  # the controller's constants (dynamics.ControllerConstants)
        self.n_substeps = int(r.sim.n_substeps)
        if r.sim.backend == "rigid":
            self.body = body_constants(r.sim.airframe)
            self.advance = self._closed_form()
        else:
            self.body, self.native = None, NativeSim(r.sim)
        self.task_names = ("prev_dist", "arrived", "crashed") + (("prev_bearing", "prev_dz") if self.v2 else ())
        self.p: dict[str, float] = {}
        self.twists: list[list[float]] = []
        self.max_steps = 0
        self.q: list[float] = []
        self.v: list[float] = []
        self.goal: list[float] = []
        self.obstacles: dict[str, np.ndarray] = {}
        self.task: dict[str, Any] = {}
        self.steps = 0
        self.obs = np.zeros(8 if self.v2 else 7, np.float32)

    def _closed_form(self) -> Any:
        """``(*qpos, *qvel, *command) -> (*qpos, *qvel)``: one control step of the closed form, written out."""
        c, body, n = self.control, self.body, self.n_substeps

        def control_step(xp, *args):
            q, v, command = list(args[:7]), list(args[7:13]), list(args[13:])
            for _ in range(n):
                q, v = physics_step(xp, body, q, v, controller(xp, c, q, v, command))
            return q + v

        names = [f"q{i}" for i in range(7)] + [f"v{i}" for i in range(6)] + [f"c{i}" for i in range(4)]
        return scalar.straight_line(control_step, names)

    def set_params(self, params: Any) -> None:
        """The task parameters of the episodes that follow, read as the float32 values the JAX step computes
        with."""
        names = goto_step.V2_PARAMS if self.v2 else goto_step.V1_PARAMS
        self.p = {k: float(np.float32(getattr(params, k))) for k in names}
        # The action map once per parameter set: each action's Twist, as the float32 command the JAX step holds.
        self.twists = [[float(np.float32(c)) for c in goto_step.twist(F, a, self.p["speed_value"])]
                       for a in range(len(goto_step.ACTION_NAMES))]
        self.max_steps = int(params.max_episode_steps)

    def start(self, states: Any, i: int) -> np.ndarray:
        """Begin an episode from the ``i``-th of ``states`` (first states of the task's reset,
        :class:`~jaxrobo.task.env.EnvState` of host arrays with a leading episode axis); its observation."""
        ps, t = states.pipeline_state, states.task
        self.q = np.asarray(ps.qpos[i], np.float64).tolist()
        self.v = np.asarray(ps.qvel[i], np.float64).tolist()
        if self.native is not None:
            self.native.reset(np.asarray(self.q), np.asarray(self.v))
        self.goal = np.asarray(t.goal[i], np.float64).tolist()
        o = t.obstacles
        self.obstacles = {"kind": np.asarray(o.kind[i]), "center": np.asarray(o.center[i], np.float64),
                          "size": np.asarray(o.size[i], np.float64), "active": np.asarray(o.active[i])}
        self.task = {n: (bool(getattr(t, n)[i]) if n in ("arrived", "crashed") else float(getattr(t, n)[i]))
                     for n in self.task_names}
        self.steps = int(states.steps[i])
        self.obs = np.asarray(states.obs[i], np.float32)
        return self.obs.copy()

    def joints(self) -> tuple[np.ndarray, np.ndarray]:
        """``(qpos, qvel)`` of the current state (float64), e.g. to draw it."""
        return np.array(self.q), np.array(self.v)

    def _advance(self, command: list[float]) -> None:
        """One control step: the cascade before every physics substep, on the backend's host physics."""
        c = self.control
        if self.native is not None:
            data = self.native.data
            self.native.advance(lambda: controller(F, c, data.qpos.tolist(), data.qvel.tolist(), command))
            self.q, self.v = data.qpos.tolist(), data.qvel.tolist()
            return
        out = self.advance(*self.q, *self.v, *command)
        self.q, self.v = list(out[:7]), list(out[7:])

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, bool, int]:
        """One step with a checked action index: ``(obs float32, reward, terminated, truncated, physics_nan,
        steps)``, as the task's ``step`` gives them."""
        self._advance(self.twists[action])
        self.steps += 1
        q, v, p = self.q, self.v, self.p
        if not math.isfinite(sum(q) + sum(v)):
            # A non-finite physics state ends the episode with zero reward and the last finite observation and
            # task variables, as the task's step does.
            return self.obs.copy(), 0.0, True, False, True, self.steps
        pos = q[:3]
        roll, pitch, yaw = euler(F, *q[3:7])
        values, dist, point = goto_step.observe(F, pos, yaw, v[2], self.goal, p, self.v2, self.kinds,
                                                goto_step.loop_fold(F, self.obstacles))
        obs = np.asarray(values, np.float32)
        if not np.all(np.isfinite(obs)):
            return self.obs.copy(), 0.0, True, False, True, self.steps
        arrived, failed = (bool(x) for x in goto_step.outcome(F, pos, roll, pitch, dist, point, p))
        # The reward reads the observation the agent gets (float32), as the task's hooks read theirs.
        seen = obs[:3].tolist()
        reward, self.task = goto_step.reward(F, p, self.task, seen, seen[0], q[2], arrived, failed, self.v2)
        terminated = arrived or failed
        self.obs = obs
        truncated = self.steps >= self.max_steps and not terminated
        return obs.copy(), float(np.float32(reward)), terminated, truncated, False, self.steps
