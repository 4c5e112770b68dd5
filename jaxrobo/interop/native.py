"""The native-MuJoCo side of the sim-to-sim check: one env on ``mujoco.MjData`` (the C engine, float64).

:class:`NativeSim` is what every port of a task to native MuJoCo (``envs/*/native.py``, flown by
``scripts/sim2sim.py``) starts from: the robot's own compiled ``MjModel``, one ``MjData``, the task's control period
in ``mj_step`` calls, a reset to a given state and the substep loop. The ports add the task's action mapping,
observation and outcome. This module imports no JAX (nor does anything it calls): the native loop is the check
that an exported policy runs without it.
"""
from __future__ import annotations

from typing import Any, Callable, Union

import mujoco
import numpy as np

#: What :meth:`NativeSim.advance` writes to ``data.ctrl`` before each ``mj_step``: the controls themselves (one
#: number per actuator, or one number for a one-actuator model), or a function of no argument returning them
#: (called before every step, e.g. an on-board controller reading the state).
Controls = Union[np.ndarray, float, Callable[[], Any]]


class NativeSim:
    """One env of a robot's model in native MuJoCo: ``model`` (the simulator's own compiled ``MjModel``),
    ``data`` (its ``MjData``) and ``n_substeps`` (``mj_step`` calls per env step: ``running_step / timestep``)."""

    def __init__(self, sim: Any):
        """``sim``: the robot's simulator (``env.robot.sim``), whose ``mj_model`` and ``n_substeps`` are used."""
        self.model = sim.mj_model
        self.data = mujoco.MjData(self.model)
        self.n_substeps = int(sim.n_substeps)

    def reset(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Back to the model's initial data (time, controls, activations, warm start), then the state
        ``(qpos, qvel)``: an episode starts from exactly the given state and nothing the last one left."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:], self.data.qvel[:] = qpos, qvel

    def advance(self, ctrl: Controls, n: int | None = None) -> None:
        """``n`` ``mj_step`` calls (default :attr:`n_substeps`: one env step), each after writing ``ctrl`` (or,
        if it is callable, ``ctrl()``) to ``data.ctrl``."""
        n = self.n_substeps if n is None else int(n)
        if not callable(ctrl):  # MuJoCo reads data.ctrl and leaves it as it is: written once, one call for all
            self.data.ctrl[:] = ctrl
            if n > 0:
                mujoco.mj_step(self.model, self.data, n)
            return
        for _ in range(n):
            self.data.ctrl[:] = ctrl()
            mujoco.mj_step(self.model, self.data)
