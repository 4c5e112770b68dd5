"""JAX's 64-bit mode is refused at the boundary with a ConfigError, before anything compiles.

x64 must be on before JAX initialises, so each check runs in a fresh interpreter with ``JAX_ENABLE_X64=1``.
"""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

import jaxrobo
from jaxrobo.core.precision import check_precision

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MESSAGE = "JAX 64-bit mode is on (jax_enable_x64=True, from the environment variable JAX_ENABLE_X64=1)"


def _run(args: list[str], tmp_path) -> subprocess.CompletedProcess:
    env = {**os.environ, "JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, *args], cwd=tmp_path, env={**env, "PYTHONPATH": ROOT},
                          capture_output=True, text=True, timeout=300)


def test_make_gym_make_sweep_and_show_refuse_x64(tmp_path):
    code = f"""
import contextlib, io, sys
import gymnasium as gym
import jax
import jaxrobo
from jaxrobo.cli import main
assert jax.config.jax_enable_x64
for call in (lambda: jaxrobo.make("CartPoleStayUp-v0"), lambda: jaxrobo.make("QuadcopterGoto-v1"),
             lambda: gym.make("jaxrobo/CartPoleStayUp-v0")):
    try:
        call()
    except jaxrobo.ConfigError as err:
        assert {MESSAGE!r} in str(err) and "unset JAX_ENABLE_X64" in str(err), err
    else:
        raise AssertionError("x64 accepted")
for argv in (["sweep", "--env", "CartPoleStayUp-v0", "--grid", "alpha=0.1,0.3", "--seeds", "1", "--out", "sw"],
             ["show", "--env", "QuadcopterGoto-v1", "--out", "f.png"]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main(argv)
    lines = err.getvalue().strip().splitlines()
    assert rc == 2 and len(lines) == 1 and lines[0].startswith(f"jaxrobo {{argv[0]}}: "), (rc, lines)
    assert {MESSAGE!r} in lines[0], lines
print("refused")
"""
    proc = _run(["-c", code], tmp_path)
    assert proc.returncode == 0 and "refused" in proc.stdout, proc.stdout + proc.stderr
    assert not os.path.exists(tmp_path / "f.png")


def test_cli_train_refuses_x64_on_one_line(tmp_path):
    proc = _run(["-m", "jaxrobo.cli", "train", "--env", "CartPoleStayUp-v0", "--n-envs", "2", "--nepisodes", "2",
                 "--no-progress", "--out", "run"], tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert len(lines) == 1 and lines[0].startswith("jaxrobo train: ") and MESSAGE in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr and not os.path.exists(tmp_path / "run")


def test_x64_switched_on_in_code_is_refused_too(monkeypatch):
    """``jax.config.update('jax_enable_x64', True)`` after import: the message points at the config call."""
    import jax

    monkeypatch.delenv("JAX_ENABLE_X64", raising=False)
    jax.config.update("jax_enable_x64", True)
    try:
        with pytest.raises(jaxrobo.ConfigError, match=r"jax.config.update\('jax_enable_x64', False\)"):
            check_precision("here")
        with pytest.raises(jaxrobo.ConfigError, match="CartPoleStayUp-v0"):
            jaxrobo.make("CartPoleStayUp-v0")
    finally:
        jax.config.update("jax_enable_x64", False)
    check_precision("here")  # 32-bit again: accepted


def test_an_env_built_without_make_is_refused_too(monkeypatch):
    """The task class called directly (no ``jaxrobo.make``) meets the same refusal when it is built, and an env
    built before x64 was switched on meets it where it is first compiled: training, the Gymnasium adapters."""
    import jax

    from envs.cartpole.stay_up import CartPoleStayUp
    from jaxrobo.interop.gym_adapter import JaxroboEnv, JaxroboVectorEnv
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    monkeypatch.delenv("JAX_ENABLE_X64", raising=False)
    spec = resolve("CartPoleStayUp-v0", overrides={"n_envs": 2, "nepisodes": 2, "nsteps": 5, "backend": "analytic"})
    built = CartPoleStayUp(CartPoleStayUp.Options(backend="analytic"))
    jax.config.update("jax_enable_x64", True)
    try:
        message = r"JAX 64-bit mode is on \(jax_enable_x64=True, from jax.config.update"
        with pytest.raises(jaxrobo.ConfigError, match=r"CartPoleStayUp\(\.\.\.\): " + message):
            CartPoleStayUp()
        with pytest.raises(jaxrobo.ConfigError, match=message):
            train(built, spec.config, spec.agent_params)
        with pytest.raises(jaxrobo.ConfigError, match=message):
            JaxroboEnv(env=built)
        with pytest.raises(jaxrobo.ConfigError, match=message):
            JaxroboVectorEnv(env=built, num_envs=2)
    finally:
        jax.config.update("jax_enable_x64", False)
    CartPoleStayUp(CartPoleStayUp.Options(backend="analytic"))  # 32-bit again: accepted
