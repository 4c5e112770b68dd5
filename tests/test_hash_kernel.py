"""The random hash as jaxlib's GPU kernel (:mod:`jaxrobo.core.hash_kernel`): when the plan calls it, that the draws
lower to it (for CUDA, lowered here on a CPU), that jax.export keeps such a program (reused traces), and that
elsewhere the hash's ops run with the same values. Its bits on a GPU: ``benchmarks/results/h200/hash_kernel.json``."""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import ClosedJaxpr

from jaxrobo.core import hash_kernel, rng
from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.training.run import resolve

TINY = {"n_envs": 2, "nepisodes": 2, "nsteps": 8, "chunk_steps": 8}


def _draws(key):
    k1, k2 = rng.split(key)
    return rng.uniform(k1, (3,)), rng.uniform_pair(k2), jax.random.key_data(rng.subkey(k1, 1, 4)), rng.bits(k2, (0,))


def _keys():
    return jax.random.split(jax.random.key(7), 4)


def _calls(jaxpr) -> int:
    """ffi calls in a closed jaxpr and the jaxprs nested in it."""
    n = 0
    for eqn in jaxpr.jaxpr.eqns:
        n += eqn.primitive.name == "ffi_call" and eqn.params.get("target_name") == hash_kernel.TARGET
        for value in eqn.params.values():
            for sub in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(sub, ClosedJaxpr):
                    n += _calls(sub)
    return n


def test_the_plan_calls_the_kernel_on_a_gpu_for_small_batches_only(monkeypatch):
    spec = resolve("QuadcopterGoto-v2", overrides=TINY)
    assert not ExecutionPlan.for_run(spec.env, spec.config, "gpu").hash_kernel  # this CPU-only JAX: not usable
    monkeypatch.setattr(hash_kernel, "usable", lambda: True)  # as on a CUDA GPU
    plan = ExecutionPlan.for_run(spec.env, spec.config, "gpu")
    assert plan.hash_kernel and "hash_kernel=on" in repr(plan) and plan.to_dict()["hash_kernel"] is True
    at_most = spec.config.replace(n_envs=hash_kernel.MAX_ENVS)
    assert ExecutionPlan.for_run(spec.env, at_most, "gpu").hash_kernel
    assert not ExecutionPlan.for_run(spec.env, at_most.replace(n_envs=hash_kernel.MAX_ENVS + 1), "gpu").hash_kernel
    assert not ExecutionPlan.for_run(spec.env, spec.config, "cpu").hash_kernel
    monkeypatch.setattr(jax, "device_count", lambda: 2)  # split over two GPUs: a partitioned program, the ops
    assert not ExecutionPlan.for_run(spec.env, spec.config.replace(devices=2), "gpu").hash_kernel
    assert "hash_kernel" not in repr(plan.replace(hash_kernel=False))
    assert plan.partitioned(1) == plan and plan.partitioned(2) == plan.replace(hash_kernel=False)  # a sweep's mesh
    with pytest.raises(ValueError, match="hash_kernel"):
        ExecutionPlan(hash_kernel=1)


def test_draws_lower_to_jaxlibs_kernel_where_chosen_and_export_keeps_them(monkeypatch):
    monkeypatch.setattr(hash_kernel, "usable", lambda: True)
    batched = jax.vmap(_draws)  # (a function traced once keeps the choice it was traced with: a new one below)
    with hash_kernel.choose(True):
        assert hash_kernel.wanted()
        lowered = jax.jit(batched).trace(_keys()).lower(lowering_platforms=("cuda",)).as_text()
        exported = jax.export.export(jax.jit(batched), platforms=("cuda",))(_keys())  # no safety check disabled
    assert lowered.count(f"@{hash_kernel.TARGET}") == 3 and "shift_left" not in lowered
    assert f"@{hash_kernel.TARGET}" in exported.mlir_module()
    with hash_kernel.choose(False):
        assert not hash_kernel.wanted()
        plain = jax.jit(jax.vmap(lambda k: _draws(k))).trace(_keys()).lower(lowering_platforms=("cuda",)).as_text()
    assert hash_kernel.TARGET not in plain and "shift_left" in plain


def test_a_tasks_reset_and_step_call_the_kernel_under_such_a_plan(monkeypatch):
    monkeypatch.setattr(hash_kernel, "usable", lambda: True)
    spec = resolve("QuadcopterGoto-v2", overrides=TINY)
    env, params = spec.env, spec.env.default_params
    key = jax.random.key(0)

    def episode(k):
        state = env.reset(k, params)
        return env.step(state, jnp.int32(1), params)

    with ExecutionPlan(hash_kernel=True).tracing():
        assert _calls(jax.make_jaxpr(episode)(key)) > 0
    assert _calls(jax.make_jaxpr(lambda k: episode(k))(key)) == 0


def test_where_the_kernel_cannot_run_the_ops_give_the_same_values_and_say_so_once():
    reason = hash_kernel.unavailable()
    assert reason and "cpu" in reason
    expected = jax.jit(jax.vmap(_draws))(_keys())
    hash_kernel._WARNED.clear()
    with pytest.warns(RuntimeWarning, match="hash_kernel: not used"):
        with ExecutionPlan(hash_kernel=True).tracing():
            assert not hash_kernel.wanted()
            got = jax.jit(jax.vmap(lambda k: _draws(k)))(_keys())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with hash_kernel.choose(True):  # said once
            pass
    for a, b in zip(jax.tree.leaves(expected), jax.tree.leaves(got)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ours = jax.jit(jax.vmap(lambda k: rng.uniform(k, (3,))))(_keys())
    theirs = jax.vmap(lambda k: jax.random.uniform(k, (3,)))(_keys())
    np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))


def test_the_version_guard(monkeypatch):
    monkeypatch.setattr(jax, "__version__", "0.13.0")
    hash_kernel.unavailable.cache_clear()
    try:
        assert "jax 0.13.0 is outside the versions the call to jaxlib's kernel" in hash_kernel.unavailable()
        assert not hash_kernel.usable()
    finally:
        monkeypatch.undo()
        hash_kernel.unavailable.cache_clear()
    assert hash_kernel.unavailable() == f"the backend is {jax.default_backend()}, not a CUDA GPU"
