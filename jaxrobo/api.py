"""The public surface for robot, task and learner authors: every name the shipped robots and tasks (``envs/``),
learners (``agents/``), the custom-task example and docs/extending.md import from jaxrobo, in one module whose
names stay where they are whatever moves inside the package (``tests/test_public_api.py`` holds the list).

A robot and a task::

    from jaxrobo.api import (BaseParams, ClosedFormSim, EnvState, JointState, LearningTarget, Robot, TaskEnv,
                             backend_choices, load_model, make_simulator, param, pytree_dataclass, register,
                             rng, spaces)

A learner::

    from jaxrobo.api import Learner, epsilon_greedy, row_max, rng

A task's port to native MuJoCo (the sim-to-sim check, ``envs/*/native.py``)::

    from jaxrobo.api import NativeSim, numpy_policy   # the observation and command an export carries

A task's step for one env on the host (``envs/cartpole/host.py``)::

    from jaxrobo.api import HostStep, NativeSim, scalar   # scalar.FLOATS: Python floats as the array module
"""
from __future__ import annotations

from jaxrobo.core import rng, scalar, spaces
from jaxrobo.core.config import ConfigError
from jaxrobo.core.struct import param, pytree_dataclass, range_param, static_field
from jaxrobo.interop import numpy_policy
from jaxrobo.interop.native import NativeSim
from jaxrobo.physics.sim import (ClosedFormSim, JointState, MjxEdit, Simulator, backend_choices, load_model,
                                 make_simulator, through_batch)
from jaxrobo.tabular import (AgentParams, AgentState, Learner, argmax_random_ties, epsilon_greedy,
                             epsilon_greedy_probabilities, greedy, greedy_probabilities, pick_among_maxima,
                             row_argmax, row_max, row_min, row_pick)
from jaxrobo.task import randomise
from jaxrobo.task.env import BaseParams, Env, EnvState, LearningTarget, TaskEnv
from jaxrobo.task.host import HostStep
from jaxrobo.task.registry import deprecated_alias, make, register
from jaxrobo.task.robot import Robot
from jaxrobo.task.rollout import greedy_policy, random_policy, rollout, success_rate

__all__ = [
    # foundation
    "ConfigError", "param", "pytree_dataclass", "range_param", "static_field", "rng", "scalar", "spaces",
    # simulators (the seed's Gazebo layer) and robots
    "ClosedFormSim", "JointState", "MjxEdit", "Simulator", "backend_choices", "load_model", "make_simulator", "through_batch",
    "NativeSim", "numpy_policy", "Robot",
    # tasks
    "BaseParams", "Env", "EnvState", "HostStep", "LearningTarget", "TaskEnv", "deprecated_alias", "make", "register",
    "randomise",
    # policies and episodes
    "greedy_policy", "random_policy", "rollout", "success_rate",
    # learners
    "AgentParams", "AgentState", "Learner", "argmax_random_ties", "epsilon_greedy", "epsilon_greedy_probabilities",
    "greedy", "greedy_probabilities", "pick_among_maxima", "row_argmax", "row_max", "row_min", "row_pick",
]
