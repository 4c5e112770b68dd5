"""docs/extending.md runs as written: its ```python blocks and its ```bash `jaxrobo ...` commands are executed in
order from examples/custom_task (on sys.path), the commands in-process with ``--out`` and other ``runs/`` paths
under tmp_path; the registry, Gymnasium, sys.modules and sys.path are restored afterwards."""
from __future__ import annotations

import os
import re
import shlex
import sys
import types

import gymnasium
import pytest

from jaxrobo.task import registry
from jaxrobo.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOC = os.path.join(ROOT, "docs", "extending.md")
EXAMPLE = os.path.join(ROOT, "examples", "custom_task")
BLOCK = re.compile(r"^```(\w+)\n(.*?)^```", re.S | re.M)


def _blocks():
    with open(DOC) as f:
        text = f.read()
    out = []
    for lang, body in BLOCK.findall(text):
        if lang == "python":
            out.append(("python", body))
        elif lang == "bash":
            for line in body.splitlines():
                if line.strip().startswith("jaxrobo "):
                    out.append(("bash", line.strip()))
    return out


@pytest.fixture
def example_dir():
    """As tests/test_user_modules.py: the example folder as cwd and on sys.path; everything restored after."""
    old_cwd, old_path = os.getcwd(), list(sys.path)
    modules = set(sys.modules)
    ids = set(registry._REGISTRY)
    gym_ids = set(gymnasium.registry)
    os.chdir(EXAMPLE)
    sys.path.insert(0, EXAMPLE)
    try:
        yield EXAMPLE
    finally:
        os.chdir(old_cwd)
        sys.path[:] = old_path
        for name in ("my_task", "my_robot"):
            if name not in modules:
                sys.modules.pop(name, None)
        for env_id in set(registry._REGISTRY) - ids:
            registry._REGISTRY.pop(env_id, None)
        for gid in set(gymnasium.registry) - gym_ids:
            gymnasium.registry.pop(gid, None)


def test_doc_has_runnable_blocks():
    kinds = [kind for kind, _ in _blocks()]
    assert kinds.count("python") >= 5 and kinds.count("bash") >= 4


@pytest.mark.slow
def test_extending_guide_runs(example_dir, tmp_path):
    # A real module: dataclasses defined in the guide look their module up in sys.modules.
    guide = types.ModuleType("extending_guide")
    sys.modules[guide.__name__] = guide
    try:
        _run(guide, tmp_path)
    finally:
        sys.modules.pop(guide.__name__, None)
    assert os.path.isfile(tmp_path / "runs" / "pendulum" / "summary.json")
    assert os.path.isfile(tmp_path / "runs" / "pendulum" / "rewards.png")
    assert os.listdir(tmp_path / "runs" / "sweep")


def _run(guide, tmp_path):
    for kind, code in _blocks():
        if kind == "python":
            exec(compile(code, DOC, "exec"), guide.__dict__)  # noqa: S102 - the guide's own examples
            continue
        argv = [str(tmp_path / a) if a.startswith("runs/") else a for a in shlex.split(code)[1:]]
        assert main(argv) == 0, code
