"""A robot and a task in the user's own module (examples/custom_task, the template a user copies): registered with
``jaxrobo.register`` from outside the package, trained with ``jaxrobo train --env my_task:MyPendulum-v0`` (the
module imported from the current directory), made with ``jaxrobo.make`` and ``gymnasium.make``; a missing module
or id is refused with exit status 2 before anything is written."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
import yaml

import jaxrobo
from jaxrobo.task import registry
from jaxrobo.cli import main
from jaxrobo.core.config import ConfigError

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLE = os.path.join(ROOT, "examples", "custom_task")
ID = "MyPendulum-v0"
TINY = ["--n-envs", "2", "--nepisodes", "3", "--no-progress", "--set", "nsteps=20", "--set", "eval_episodes=2",
        "--set", "eval_envs=1"]


def _forget(module_names, ids):
    for name in module_names:
        sys.modules.pop(name, None)
    for env_id in ids:
        registry._REGISTRY.pop(env_id, None)
        gymnasium.registry.pop(f"jaxrobo/{env_id}", None)
        gymnasium.registry.pop(env_id, None)


@pytest.fixture(scope="module")
def example_dir():
    """The example folder as the current directory, its modules not yet imported; afterwards the registry,
    Gymnasium, sys.modules and sys.path are as before (other tests iterate over the registered ids)."""
    old_cwd, old_path = os.getcwd(), list(sys.path)
    os.chdir(EXAMPLE)
    try:
        yield EXAMPLE
    finally:
        os.chdir(old_cwd)
        sys.path[:] = old_path
        _forget(["my_task", "my_robot", "my_other_task"], [ID, "MyOtherPendulum-v0"])


def test_train_a_user_module_task_from_its_folder(example_dir, tmp_path):
    """`jaxrobo train --env my_task:MyPendulum-v0` from the example folder (not on sys.path: the CLI adds the
    current directory) writes a run whose config.yaml records the module, with the YAML files beside it."""
    out = str(tmp_path / "run")
    assert main(["train", "--env", f"my_task:{ID}", *TINY, "--out", out]) == 0
    assert {"config.yaml", "summary.json", "episodes.csv", "qtables.npz"} <= set(os.listdir(out))
    with open(os.path.join(out, "config.yaml")) as f:
        config = yaml.safe_load(f)
    assert config["env_id"] == f"my_task:{ID}"
    assert config["env_params"]["max_episode_steps"] == 200  # from my_task.yaml beside the module
    assert config["train"]["bins"] == [8, 8] and config["agent_params"]["alpha"] == 0.3  # my_task_agent.yaml
    assert config["train"]["nsteps"] == 20  # --set over the preset
    with open(os.path.join(out, "summary.json")) as f:
        assert json.load(f)["env_id"] == ID

    # --resume runs in another process: the saved 'module:Id' imports the module again from the run's folder, as
    # `--resume DIR --env my_task:Id` asks (a config.yaml alone never imports code).
    code = ("import sys, yaml; from jaxrobo.training.run import spec_from_config; "
            f"spec = spec_from_config(yaml.safe_load(open({os.path.join(out, 'config.yaml')!r})), "
            f"trusted_env='my_task:{ID}'); "
            "print(spec.env_id, spec.env.default_params.max_episode_steps)")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
    done = subprocess.run([sys.executable, "-c", code], cwd=EXAMPLE, env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [ID, "200"]


def test_make_and_gym_make_after_import(example_dir):
    env = jaxrobo.make(f"my_task:{ID}", max_torque=1.0)
    assert env.spec.id == ID and env.spec.max_episode_steps == 200
    assert float(env.default_params.max_torque) == 1.0 and env.num_actions == 3
    spec = registry.spec(ID)
    assert spec.config == os.path.join(EXAMPLE, "my_task.yaml")  # relative to the registering module
    assert spec.agent_config == os.path.join(EXAMPLE, "my_task_agent.yaml")
    assert registry.qualified_id(ID) == f"my_task:{ID}" and registry.qualified_id("CartPoleStayUp-v0") == \
        "CartPoleStayUp-v0"
    # registered after `import jaxrobo`: a Gymnasium id too, with the env YAML's step limit
    assert gymnasium.spec(f"jaxrobo/{ID}").max_episode_steps == 200
    genv = gymnasium.make(f"jaxrobo/{ID}")
    obs, _ = genv.reset(seed=0)
    assert obs.shape == (2,) and np.all(np.abs(obs) <= 0.05 + 1e-6)
    obs, reward, terminated, truncated, _ = genv.step(1)
    assert obs.shape == (2,) and reward == 1.0 and not truncated
    genv.close()


def test_gymnasiums_own_module_id_form_in_a_fresh_process(example_dir):
    """``gymnasium.make("my_task:MyPendulum-v0")``, Gymnasium's ``module:Id``, with nothing imported before: Gymnasium
    imports my_task, whose register call makes the id a Gymnasium id under both names at once (no
    register_gymnasium_envs() needed); a built-in id keeps only its ``jaxrobo/`` name."""
    code = ("import gymnasium; e = gymnasium.make('my_task:MyPendulum-v0'); obs, _ = e.reset(seed=0); "
            "v = gymnasium.make_vec('my_task:jaxrobo/MyPendulum-v0', num_envs=2); "
            "print(e.spec.id, e.spec.max_episode_steps, obs.shape, v.num_envs, "
            "'CartPoleStayUp-v0' in gymnasium.registry, 'jaxrobo/CartPoleStayUp-v0' in gymnasium.registry)")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
    done = subprocess.run([sys.executable, "-c", code], cwd=EXAMPLE, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [ID, "200", "(2,)", "2", "False", "True"]


def test_register_paths_beside_the_module_or_absolute(example_dir, tmp_path):
    """A module elsewhere registers with a relative path (beside it) and an absolute one; ':' is not an id."""
    agent_yaml = tmp_path / "agent.yaml"
    agent_yaml.write_text("default:\n  alpha: 0.2\n  bins: [4, 4]\n")
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "env.yaml").write_text("env:\n  max_episode_steps: 30\n")
    (tmp_path / "my_other_task.py").write_text(
        "import jaxrobo\nfrom my_task import MyPendulum\n"
        "jaxrobo.register('MyOtherPendulum-v0', MyPendulum, config='cfg/env.yaml', "
        f"agent_config={str(agent_yaml)!r})\n")
    registry.find(f"my_task:{ID}")  # my_other_task imports my_task: from the current directory, now on sys.path
    sys.path.insert(0, str(tmp_path))
    env = jaxrobo.make("my_other_task:MyOtherPendulum-v0")
    assert env.spec.max_episode_steps == 30
    spec = registry.spec("MyOtherPendulum-v0")
    assert spec.config == str(tmp_path / "cfg" / "env.yaml") and spec.agent_config == str(agent_yaml)
    from jaxrobo.training.run import agent_presets

    assert agent_presets("my_other_task:MyOtherPendulum-v0")["default"]["alpha"] == 0.2
    with pytest.raises(ValueError, match="without ':'"):
        jaxrobo.register("a:b", "x:Y")


@pytest.mark.parametrize("env_id, message", [
    ("no_such_module_xyz:MyPendulum-v0", r"--env no_such_module_xyz:MyPendulum-v0: environment id: no module "
                                          r"named 'no_such_module_xyz'"),
    ("my_task:NoSuchId-v0", r"--env my_task:NoSuchId-v0: environment id: module 'my_task' does not register "
                            r"'NoSuchId-v0'; it registers MyPendulum-v0"),
    ("NoSuchId-v0", r"--env NoSuchId-v0: environment id: unknown key 'NoSuchId-v0'"),
])
@pytest.mark.parametrize("command", ["train", "sweep"])
def test_a_missing_module_or_id_is_refused_before_anything_is_written(example_dir, tmp_path, capsys, env_id,
                                                                      message, command):
    out = tmp_path / "out"
    args = [command, "--env", env_id, "--out", str(out), "--n-envs", "2", "--nepisodes", "2"]
    args += ["--grid", "alpha=0.1,0.2"] if command == "sweep" else []
    assert main(args) == 2
    assert not out.exists() and os.listdir(tmp_path) == []
    err = capsys.readouterr().err
    assert re.search(message, err), err


def test_make_names_the_missing_module(example_dir):
    with pytest.raises(ConfigError, match=r"no module named 'no_such_module_xyz'"):
        jaxrobo.make("no_such_module_xyz:X-v0")
    with pytest.raises(ConfigError, match=r"expected 'module:Id'"):
        jaxrobo.make("my_task:")


def test_check_runs_gymnasium_on_a_user_module_id(example_dir):
    """`jaxrobo check my_task:MyPendulum-v0`: Gymnasium's checker runs on the bare id the module registered
    (jaxrobo/MyPendulum-v0), also when that Gymnasium registration is missing."""
    from jaxrobo.check import check_env

    for forget in (False, True):
        if forget:
            gymnasium.registry.pop(f"jaxrobo/{ID}", None)
        (result,) = check_env(f"my_task:{ID}", checks=("gymnasium",))
        assert result.status == "ok", result.message
        assert f"gymnasium.make('jaxrobo/{ID}')" in result.message
    assert f"jaxrobo/{ID}" in gymnasium.registry
