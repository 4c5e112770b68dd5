"""The public surface for robot, task and learner authors (:mod:`jaxrobo.api`) is stable: its names are listed
here and each resolves; module paths the package does not hold (the flat ``jaxrobo.env``, ``jaxrobo.sim``, ...)
are not aliased into existence. A change to this list is a change to what users' modules may rely on: make it on
purpose."""
from __future__ import annotations

import sys

import jaxrobo
import jaxrobo.api as api

#: The names of jaxrobo.api. Add to it freely; removing or renaming one breaks users' modules.
PUBLIC = {
    "ConfigError", "param", "pytree_dataclass", "range_param", "static_field", "rng", "scalar", "spaces",
    "ClosedFormSim", "JointState", "MjxEdit", "Simulator", "backend_choices", "load_model", "make_simulator",
    "through_batch", "actuators", "NativeSim", "numpy_policy", "Robot", "BaseParams", "Env", "EnvState", "HostStep",
    "LearningTarget", "TaskEnv", "deprecated_alias", "make", "register",
    "randomise", "greedy_policy", "random_policy", "rollout", "success_rate",
    "AgentParams", "AgentState", "Learner", "argmax_random_ties", "epsilon_greedy", "epsilon_greedy_probabilities",
    "greedy", "greedy_probabilities", "pick_among_maxima", "row_argmax", "row_max", "row_min", "row_pick",
}


def test_api_names_are_the_listed_ones_and_resolve():
    assert set(api.__all__) == PUBLIC
    for name in PUBLIC:
        assert getattr(api, name) is not None, name
    # the package root's names are the same objects
    assert jaxrobo.TaskEnv is api.TaskEnv and jaxrobo.make is api.make and jaxrobo.Robot is api.Robot


def test_no_aliases_for_module_paths_the_package_does_not_hold():
    """``jaxrobo.env``, ``jaxrobo.sim`` and the other flat names were never released: importing one fails, and
    the package root carries no attribute of that name (user modules import :mod:`jaxrobo.api`)."""
    import importlib

    for name in ("env", "robot", "registry", "rollout", "sim", "struct", "spaces", "rng", "config"):
        assert f"jaxrobo.{name}" not in sys.modules, name
        assert not hasattr(jaxrobo, name), name
        try:
            importlib.import_module(f"jaxrobo.{name}")
        except ModuleNotFoundError:
            continue
        raise AssertionError(f"jaxrobo.{name} imports")
