"""The public surface for robot, task and learner authors (:mod:`jaxrobo.api`) is stable: its names are listed
here, each resolves, and modules written against the earlier flat layout (``jaxrobo.env``, ``jaxrobo.sim``, ...)
still import. A change to this list is a change to what users' modules may rely on: make it on purpose."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import jaxrobo
import jaxrobo.api as api

#: The names of jaxrobo.api. Add to it freely; removing or renaming one breaks users' modules.
PUBLIC = {
    "ConfigError", "param", "pytree_dataclass", "range_param", "static_field", "rng", "spaces",
    "ClosedFormSim", "JointState", "MjxEdit", "Simulator", "backend_choices", "load_model", "make_simulator", "through_batch",
    "NativeSim", "Robot", "BaseParams", "Env", "EnvState", "LearningTarget", "TaskEnv", "deprecated_alias", "make", "register",
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


def test_legacy_flat_module_paths_still_import():
    """A module written against the flat layout (before the subpackages) imports the same objects."""
    import jaxrobo.env
    import jaxrobo.sim
    from jaxrobo import rng, spaces
    from jaxrobo.env import BaseParams, TaskEnv
    from jaxrobo.robot import Robot
    from jaxrobo.struct import param, pytree_dataclass
    from jaxrobo.tabular import Learner, epsilon_greedy

    assert TaskEnv is api.TaskEnv and BaseParams is api.BaseParams and Robot is api.Robot
    assert param is api.param and pytree_dataclass is api.pytree_dataclass
    assert rng is api.rng and spaces is api.spaces and jaxrobo.sim.load_model is api.load_model
    assert jaxrobo.env.EnvState is api.EnvState and Learner is api.Learner and epsilon_greedy is api.epsilon_greedy
    for old, new in jaxrobo.LEGACY_MODULES.items():
        assert sys.modules[f"jaxrobo.{old}"] is sys.modules[new]


def test_a_legacy_user_module_imports_in_a_fresh_process(tmp_path):
    """In a fresh interpreter, ``from jaxrobo.env import ...`` as the first jaxrobo import works too (the package
    is initialised on the way and maps the old names)."""
    (tmp_path / "old_task.py").write_text(textwrap.dedent("""
        from jaxrobo.struct import param, pytree_dataclass
        from jaxrobo.env import BaseParams, TaskEnv
        from jaxrobo.sim import load_model, make_simulator
        from jaxrobo import spaces, rng
        import jaxrobo.api
        assert TaskEnv is jaxrobo.api.TaskEnv and spaces is jaxrobo.api.spaces
        print("ok")
    """))
    out = subprocess.run([sys.executable, "-c", "import old_task"], cwd=tmp_path, capture_output=True, text=True,
                         env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"}, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]
