"""The persistent compilation cache: where it lives, how to turn it off, and that a second process reuses it."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from jaxrobo import cache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, os, sys, time
sys.path.insert(0, sys.argv[1])
from jaxrobo.cache import enable_compilation_cache, entries
d = enable_compilation_cache()
import jax, jax.numpy as jnp
before = entries(d)
f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + 1.0)
y = f(jnp.ones((8, 8)))
y.block_until_ready()
print(json.dumps({"dir": d, "before": before, "after": entries(d)}))
"""


def test_cache_dir_resolution(monkeypatch, tmp_path):
    monkeypatch.delenv(cache.ENV_VAR, raising=False)
    assert cache.cache_dir() == os.path.expanduser(os.path.join("~", ".cache", "jaxrobo", "jax"))
    monkeypatch.setenv(cache.ENV_VAR, str(tmp_path / "c"))
    assert cache.cache_dir() == str(tmp_path / "c")
    for off in ("off", "OFF", "0", "none", ""):
        monkeypatch.setenv(cache.ENV_VAR, off)
        assert cache.cache_dir() is None
        assert cache.enable_compilation_cache() is None
    assert cache.cache_dir(str(tmp_path / "x")) == str(tmp_path / "x")


def _child(env):
    out = subprocess.run([sys.executable, "-c", CHILD, ROOT], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_second_process_reads_the_cache(tmp_path):
    env = {**os.environ, cache.ENV_VAR: str(tmp_path / "jax"), "JAX_PLATFORMS": "cpu"}
    first = _child(env)
    assert first["dir"] == str(tmp_path / "jax")
    assert first["before"] == 0 and first["after"] > 0  # a sub-second compile is cached too
    second = _child(env)
    assert second["before"] == second["after"] == first["after"]  # served from the cache, nothing new written


def test_off_writes_nothing(tmp_path):
    env = {**os.environ, cache.ENV_VAR: "off", "JAX_PLATFORMS": "cpu"}
    assert _child(env)["dir"] is None


def test_exported_jit_matches_jit_and_reloads(tmp_path):
    """A traced program kept with jax.export gives the same numbers as jax.jit, and is loaded, not re-traced."""
    import jax
    import jax.numpy as jnp
    import pytest

    pytest.importorskip("flatbuffers")
    traces = []

    def step(state, scale):
        traces.append(1)
        key, sub = jax.random.split(state["key"])
        return {"key": key, "x": state["x"] * scale + jax.random.uniform(sub, state["x"].shape)}

    state = {"key": jax.random.key(3), "x": jnp.arange(4.0)}
    want = jax.jit(step)(state, 2.0)
    first = cache.exported_jit(step, (state, 2.0), state, "test-step", directory=str(tmp_path))
    got = first(state, 2.0)
    assert os.listdir(tmp_path / "exported")
    n = len(traces)
    again = cache.exported_jit(step, (state, 2.0), state, "test-step", directory=str(tmp_path))
    assert len(traces) == n  # loaded from disk: no Python tracing
    got2 = again(state, 2.0)
    for a, b in ((want, got), (want, got2)):
        assert jnp.array_equal(a["x"], b["x"])
        assert jnp.array_equal(jax.random.key_data(a["key"]), jax.random.key_data(b["key"]))


def test_train_keeps_its_traced_chunk_and_gives_the_same_result(tmp_path, monkeypatch):
    """train() with the chunk's traced program kept (first run: exported; second: loaded) equals a plain jit run."""
    import numpy as np
    import pytest

    import jaxrobo
    from jaxrobo.train import TrainConfig, train

    pytest.importorskip("flatbuffers")
    env = jaxrobo.make("CartPoleStayUp-v0", backend="analytic")
    config = TrainConfig(n_envs=4, nepisodes=3, nsteps=60, chunk_steps=30, seed=5, eval_episodes=0)
    results = []
    for directory in (None, str(tmp_path), str(tmp_path)):
        monkeypatch.setattr(cache, "_current_dir", lambda d=directory: d)
        results.append(train(env, config))
        if directory is not None:
            assert len(os.listdir(tmp_path / "exported")) == 1  # written once, then loaded
    for got in results[1:]:
        np.testing.assert_array_equal(got.q, results[0].q)
        np.testing.assert_array_equal(got.returns, results[0].returns)
        assert got.env_steps == results[0].env_steps


def test_only_own_code_keys_a_kept_program():
    import jaxrobo

    env = jaxrobo.make("CartPoleStayUp-v0", backend="analytic")
    assert cache.is_own_code(env, env.robot, env.robot.sim)
    assert not cache.is_own_code(env, lambda x: x)  # defined here, outside jaxrobo/envs/agents
