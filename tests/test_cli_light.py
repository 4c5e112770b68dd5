"""Commands that must stay light or say what they are: ``jaxrobo list`` never imports MJX (seconds of import on a
CPU), and a ``--preset seed`` run says it is the seed's baseline and what it costs in memory."""
from __future__ import annotations

import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_list_imports_neither_mjx_nor_brax():
    code = ("import sys; from jaxrobo.cli import main; main(['list']); "
            "print(sorted(m for m in ('mujoco.mjx', 'brax', 'matplotlib') if m in sys.modules))")
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "CartPoleStayUp-v0" in out.stdout and out.stdout.strip().splitlines()[-1] == "[]"


def test_seed_preset_says_it_is_the_seeds_baseline_and_its_memory():
    from jaxrobo.cli import seed_preset_note
    from jaxrobo.training.budget import estimate, format_bytes
    from jaxrobo.training.run import check_discretiser, resolve

    spec = resolve("CartPoleStayUp-v0", "seed", {"n_envs": 2}, check_memory=False)
    note = seed_preset_note(spec)
    total = estimate(spec.env, spec.config, check_discretiser(spec.env, spec.config))["total"]
    assert note.startswith("preset seed: the seed's baseline") and "not tuned to learn" in note
    assert f"memory about {format_bytes(total)}" in note


def test_a_deprecated_env_id_is_said_once_in_one_line(tmp_path):
    """``--env`` given a deprecated id: the command says so once, as one line naming the command (not Python's
    file:line and source line, once per place that looked the id up), and runs the id it stands for."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, "-m", "jaxrobo.cli", "train", "--env", "CartPoleStayUp-v1", "--n-envs", "2",
                          "--nepisodes", "2", "--set", "nsteps=10", "--set", "eval_episodes=0", "--no-progress",
                          "--out", str(tmp_path / "run")], capture_output=True, text=True, env=env, cwd=ROOT,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    said = [line for line in out.stderr.splitlines() if "deprecated" in line]
    assert said == ["jaxrobo train: FutureWarning: environment id 'CartPoleStayUp-v1' is deprecated: it is "
                    "'CartPoleStayUpLeftRight-v0'"], out.stderr
    assert "CartPoleStayUpLeftRight-v0" in (tmp_path / "run" / "config.yaml").read_text()
