"""jaxrobo: the openai_ros training structure (task → robot → sim → env) as functional JAX on MuJoCo MJX.

>>> import jax, jaxrobo
>>> env = jaxrobo.make("CartPoleStayUp-v0", control_type="position")
>>> state = env.reset(jax.random.key(0))
>>> state = env.step(state, 1)

Public surface: :func:`make`, :func:`register`, :func:`registered`, :func:`spec` (:mod:`jaxrobo.registry`); to
write a task, subclass :class:`TaskEnv` (:mod:`jaxrobo.env`); a robot, :class:`Robot` (:mod:`jaxrobo.robot`),
whose simulator comes from :func:`make_simulator`, with a hand-written backend on :class:`ClosedFormSim`
(:mod:`jaxrobo.sim`). Training, sweeps, plots and videos are the ``jaxrobo`` CLI and :mod:`jaxrobo.train`,
:mod:`jaxrobo.sweep`, :mod:`jaxrobo.render`; the Gymnasium ids ``jaxrobo/<id>`` are :mod:`jaxrobo.gym_adapter`.
"""
from __future__ import annotations

__version__ = "0.1.0"

from jaxrobo.render import select_gl_backend as _select_gl

_select_gl()  # before anything imports mujoco: MUJOCO_GL may only name a backend whose library loads

from jaxrobo.config import ConfigError
from jaxrobo.env import EnvState, TaskEnv
from jaxrobo.registry import make, register, registered, spec
from jaxrobo.robot import Robot
from jaxrobo.sim import ClosedFormSim, make_simulator
from jaxrobo import gym_adapter as _gym_adapter  # noqa: E402,F401  (registers "jaxrobo/<id>" with Gymnasium)

__all__ = ["ClosedFormSim", "ConfigError", "EnvState", "Robot", "TaskEnv", "make", "make_simulator", "register",
           "registered", "spec", "__version__"]
