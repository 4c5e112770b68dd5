"""jaxrobo: the openai_ros training structure (task → robot → sim → env) as functional JAX on MuJoCo MJX.

>>> import jax, jaxrobo
>>> env = jaxrobo.make("CartPoleStayUp-v0", control_type="position")
>>> state = env.reset(jax.random.key(0))
>>> state = env.step(state, 1)

Public surface: :func:`make`, :func:`register`, :func:`registered`, :func:`spec` (:mod:`jaxrobo.task.registry`); to
write a task, subclass :class:`TaskEnv` (:mod:`jaxrobo.task.env`); a robot, :class:`Robot` (:mod:`jaxrobo.task.robot`),
whose simulator comes from :func:`make_simulator`, with a hand-written backend on :class:`ClosedFormSim`
(:mod:`jaxrobo.physics.sim`). Training, sweeps, plots and videos are the ``jaxrobo`` CLI and :mod:`jaxrobo.training.train`,
:mod:`jaxrobo.training.sweep`, :mod:`jaxrobo.pictures.render`; the Gymnasium ids ``jaxrobo/<id>`` are :mod:`jaxrobo.interop.gym_adapter`.
"""
from __future__ import annotations

from jaxrobo.core.version import __version__

from jaxrobo.core.environ import check_before_import as _check_environ

_check_environ()  # before JAX and MuJoCo read JAX_ENABLE_X64 / MUJOCO_GL at import and fail with a traceback

from jaxrobo.pictures.render import select_gl_backend as _select_gl

_select_gl()  # before anything imports mujoco: MUJOCO_GL may only name a backend whose library loads

from jaxrobo.core.config import ConfigError
from jaxrobo.task.env import EnvState, TaskEnv
from jaxrobo.task.registry import make, register, registered, spec
from jaxrobo.task.robot import Robot
from jaxrobo.physics.sim import ClosedFormSim, make_simulator
from jaxrobo.interop import gym_adapter as _gym_adapter  # noqa: E402,F401  (registers "jaxrobo/<id>" with Gymnasium)

__all__ = ["ClosedFormSim", "ConfigError", "EnvState", "Robot", "TaskEnv", "make", "make_simulator", "register",
           "registered", "spec", "__version__"]
