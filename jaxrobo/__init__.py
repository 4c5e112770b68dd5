"""jaxrobo: the openai_ros training structure (task → robot → sim → env) as functional JAX on MuJoCo MJX.

>>> import jax, jaxrobo
>>> env = jaxrobo.make("CartPoleStayUp-v0", control_type="position")
>>> state = env.reset(jax.random.key(0))
>>> state = env.step(state, 1)

Public surface: :func:`make`, :func:`register`, :func:`registered`, :func:`spec` (:mod:`jaxrobo.task.registry`); to
write a task, subclass :class:`TaskEnv` (:mod:`jaxrobo.task.env`); a robot, :class:`Robot` (:mod:`jaxrobo.task.robot`),
whose simulator comes from :func:`make_simulator`, with a hand-written backend on :class:`ClosedFormSim`
(:mod:`jaxrobo.physics.sim`). Training, sweeps, plots and videos are the ``jaxrobo`` CLI and
:mod:`jaxrobo.training.train`, :mod:`jaxrobo.training.sweep`, :mod:`jaxrobo.pictures.render`; the Gymnasium ids
``jaxrobo/<id>`` are :mod:`jaxrobo.interop.gym_ids` (registered here) and :mod:`jaxrobo.interop.gym_adapter` (the envs).

``import jaxrobo`` loads neither JAX nor MuJoCo: the registry, the Gymnasium ids and :class:`ConfigError` need
neither, and the names that do are imported on first access.
"""
from __future__ import annotations

import importlib
import importlib.util

from jaxrobo.core.version import __version__

from jaxrobo.core.environ import check_before_import as _check_environ

_check_environ()  # before JAX and MuJoCo read JAX_ENABLE_X64 / MUJOCO_GL at import and fail with a traceback

from jaxrobo.pictures.render import select_gl_backend as _select_gl

_select_gl()  # before anything imports mujoco: MUJOCO_GL may only name a backend whose library loads

from jaxrobo.core.config import ConfigError
from jaxrobo.task.registry import make, register, registered, spec
from jaxrobo.interop import gym_ids as _gym_ids  # noqa: E402,F401  (registers "jaxrobo/<id>" with Gymnasium, no JAX)

#: The public names whose modules import JAX (or MuJoCo), by module: imported on first access (PEP 562), so that
#: ``import jaxrobo`` (the CLI's start, a native port, an id lookup) loads neither.
_LAZY = {"EnvState": "jaxrobo.task.env", "TaskEnv": "jaxrobo.task.env", "Robot": "jaxrobo.task.robot",
         "ClosedFormSim": "jaxrobo.physics.sim", "make_simulator": "jaxrobo.physics.sim"}

__all__ = ["ClosedFormSim", "ConfigError", "EnvState", "Robot", "TaskEnv", "make", "make_simulator", "register",
           "registered", "spec", "__version__"]


def __getattr__(name: str):
    """A lazy public name (:data:`_LAZY`), or a subpackage or module of jaxrobo (``jaxrobo.training``) imported on
    first access as ``import jaxrobo.training`` would."""
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
