"""The public surface for robot, task and learner authors: every name the shipped robots and tasks (``envs/``),
learners (``agents/``), the custom-task example and docs/extending.md import from jaxrobo, in one module whose
names stay where they are whatever moves inside the package (``tests/test_public_api.py`` holds the list).
Each name is imported from its module on first access (PEP 562), so ``from jaxrobo.api import register, scalar``
(the built-in ids' registration, a host step's floats) loads no JAX; a name whose module needs JAX imports it.

A robot and a task::

    from jaxrobo.api import (BaseParams, ClosedFormSim, EnvState, JointState, LearningTarget, Robot, TaskEnv,
                             backend_choices, load_model, make_simulator, param, pytree_dataclass, register,
                             rng, spaces)
    from jaxrobo.api import actuators   # a hand-written backend's MuJoCo joint actuators

A learner::

    from jaxrobo.api import Learner, epsilon_greedy, row_max, rng

A task's port to native MuJoCo (the sim-to-sim check, ``envs/*/native.py``)::

    from jaxrobo.api import NativeSim, numpy_policy   # the observation and command an export carries

A task's step for one env on the host (``envs/cartpole/host.py``)::

    from jaxrobo.api import HostStep, NativeSim, scalar   # scalar.FLOATS: Python floats as the array module
"""
from __future__ import annotations

import importlib

#: Every public name by the module that defines it, grouped as users meet them.
_HOMES: dict[str, tuple[str, ...]] = {
    # foundation
    "jaxrobo.core.config": ("ConfigError",),
    "jaxrobo.core.struct": ("param", "pytree_dataclass", "range_param", "static_field"),
    # simulators (the seed's Gazebo layer) and robots
    "jaxrobo.physics.sim": ("ClosedFormSim", "JointState", "MjxEdit", "Simulator", "backend_choices", "load_model",
                            "make_simulator", "through_batch"),
    "jaxrobo.interop.native": ("NativeSim",),
    "jaxrobo.task.robot": ("Robot",),
    # tasks
    "jaxrobo.task.env": ("BaseParams", "Env", "EnvState", "LearningTarget", "TaskEnv"),
    "jaxrobo.task.host": ("HostStep",),
    "jaxrobo.task.registry": ("deprecated_alias", "make", "register"),
    # policies and episodes
    "jaxrobo.task.rollout": ("greedy_policy", "random_policy", "rollout", "success_rate"),
    # learners
    "jaxrobo.tabular": ("AgentParams", "AgentState", "Learner", "argmax_random_ties", "epsilon_greedy",
                        "epsilon_greedy_probabilities", "greedy", "greedy_probabilities", "pick_among_maxima",
                        "row_argmax", "row_max", "row_min", "row_pick"),
}
#: The public modules, by the name they go by here.
_MODULES = {name.rpartition(".")[2]: name for name in ("jaxrobo.core.rng", "jaxrobo.core.scalar", "jaxrobo.core.spaces",
                                                        "jaxrobo.interop.numpy_policy", "jaxrobo.task.randomise",
                                                        "jaxrobo.physics.actuators")}
_HOME = {name: module for module, names in _HOMES.items() for name in names}

__all__ = [*_HOME, *_MODULES]


def __getattr__(name: str):
    if name in _MODULES:
        return importlib.import_module(_MODULES[name])
    if name in _HOME:
        return getattr(importlib.import_module(_HOME[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
