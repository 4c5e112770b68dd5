"""The persistent compilation cache: where it lives, how to turn it off, and that a second process reuses it."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from jaxrobo.speed import cache

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, os, sys, time
sys.path.insert(0, sys.argv[1])
from jaxrobo.speed.cache import enable_compilation_cache, entries
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


TRAIN_CHILD = r"""
import hashlib, json, sys
sys.path.insert(0, sys.argv[1])
from jaxrobo.speed.cache import enable_compilation_cache, entries
d = enable_compilation_cache()
import jax, jax.numpy as jnp, numpy as np
import jaxrobo
from envs.cartpole.dynamics import CartPoleSim
from jaxrobo.training.trainer import TrainConfig
from jaxrobo.training.train import train

env = jaxrobo.make("CartPoleStayUp-v0", backend="analytic")
config = TrainConfig(n_envs=4, nepisodes=3, nsteps=40, chunk_steps=40, seed=5, eval_episodes=0)


def run():
    r = train(env, config)
    digest = hashlib.sha256(np.asarray(r.q).tobytes() + np.asarray(r.returns).tobytes()).hexdigest()
    from jaxrobo.speed import reuse

    return {"digest": digest, "nan_episodes": int(r.nan_episodes.sum()), "entries": entries(d),
            "chunk": reuse.LAST.get("chunk", "off")}


out = {}
if "patch" in sys.argv[2:]:
    step = CartPoleSim.physics_step
    # the kind of physics blow-up a user can patch in at run time: every state becomes NaN
    CartPoleSim.physics_step = lambda self, s, ctrl: jax.tree.map(lambda x: x * jnp.nan, step(self, s, ctrl))
    out["patched"] = run()
    CartPoleSim.physics_step = step
out["plain"] = run()
print(json.dumps(out))
"""


def _train_child(env, *args):
    out = subprocess.run([sys.executable, "-c", TRAIN_CHILD, ROOT, *args], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_warm_cache_never_serves_stale_training_code(tmp_path):
    """With the cache filled by a first process, a second process that patches the physics step at run time
    trains with the patched step (its NaN episodes are counted), and after undoing the patch trains exactly as the
    first process did, reading the first process's compiles instead of writing new ones. With traces reused
    (jaxrobo.speed.reuse), as a user's runs do: the patched step is another key, the undone patch the first one."""
    env = {**os.environ, cache.ENV_VAR: str(tmp_path / "jax"), "JAX_PLATFORMS": "cpu", "JAXROBO_REUSE_TRACES": "on"}
    first = _train_child(env)["plain"]
    assert first["nan_episodes"] == 0 and first["entries"] > 0 and first["chunk"] == "traced"
    second = _train_child(env, "patch")
    assert second["patched"]["chunk"] == "traced" and second["plain"]["chunk"] == "read"
    assert second["patched"]["nan_episodes"] > 0  # training ran the patched step, not the cached one
    assert second["patched"]["digest"] != first["digest"]
    assert second["patched"]["entries"] > first["entries"]  # another program, so another compile
    assert second["plain"]["nan_episodes"] == 0
    assert second["plain"]["digest"] == first["digest"]  # the original code again, the original results
    assert second["plain"]["entries"] == second["patched"]["entries"]  # served from the first process's cache
