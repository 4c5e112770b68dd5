"""jaxrobo.interop.brax_compat: the JAX shim for Brax's trainers and the SAC evaluator swap, and their Brax version
guard."""
from __future__ import annotations

import jax
import numpy as np
import pytest
from brax.training import acting

from jaxrobo.interop import brax_compat


@pytest.fixture(autouse=True)
def fresh_warnings(monkeypatch):
    monkeypatch.setattr(brax_compat, "_WARNED", set())  # each test sees its own once-only warnings


def test_installed_brax_is_in_range_and_the_guard_trips_outside_it():
    assert brax_compat.unavailable() is None, brax_compat.unavailable()
    low, high = brax_compat.WRITTEN_FOR
    assert brax_compat.unavailable(f"{low[0]}.{low[1]}.0") is None
    for version in (f"{high[0]}.{high[1]}.0", "0.13.9", "1.0.0", "nightly"):
        reason = brax_compat.unavailable(version)
        assert reason is not None and version in reason and "written for" in reason


def test_jax_shim_is_a_no_op_where_jax_has_the_functions(monkeypatch):
    def mine(*args):
        raise AssertionError("not to be called")

    for name in brax_compat.JAX_FUNCTIONS:
        monkeypatch.setattr(jax, name, mine, raising=False)
    assert brax_compat.install_jax_compat() == []
    assert brax_compat.install_jax_compat("0.99.0") == []  # nothing to do, so no guard either
    assert all(getattr(jax, name) is mine for name in brax_compat.JAX_FUNCTIONS)


def test_jax_shim_fills_in_what_jax_lacks_and_warns_outside_the_range(monkeypatch):
    for name in brax_compat.JAX_FUNCTIONS:
        monkeypatch.delattr(jax, name, raising=False)
    assert brax_compat.install_jax_compat() == list(brax_compat.JAX_FUNCTIONS)
    devices = jax.devices()[:1]
    rep = jax.device_put_replicated({"a": np.arange(3.0)}, devices)
    np.testing.assert_array_equal(np.asarray(rep["a"]), [[0.0, 1.0, 2.0]])
    sharded = jax.device_put_sharded([np.full(2, 5.0)], devices)
    np.testing.assert_array_equal(np.asarray(sharded), [[5.0, 5.0]])

    for name in brax_compat.JAX_FUNCTIONS:
        monkeypatch.delattr(jax, name)
    with pytest.warns(RuntimeWarning, match=r"brax 0\.99\.0 is outside the versions"):
        assert brax_compat.install_jax_compat("0.99.0") == list(brax_compat.JAX_FUNCTIONS)
    assert callable(jax.device_put_replicated)


def test_evaluator_swap_keeps_params_and_restores_the_original_even_when_training_raises():
    original = acting.Evaluator
    with pytest.raises(KeyboardInterrupt):
        with brax_compat.keep_evaluator_params() as hook:
            assert acting.Evaluator is not original and issubclass(acting.Evaluator, original)
            out = acting.Evaluator.run_evaluation(None, "params-1", {"loss": 1.0})
            assert out == {"loss": 1.0} and hook.has_params and hook.pop() == "params-1" and not hook.has_params
            raise KeyboardInterrupt
    assert acting.Evaluator is original
    assert hook.calls == 1
    hook.check()  # it saw parameters


def test_sac_training_restores_the_evaluator_when_the_trainer_raises(monkeypatch):
    """training._train_sac through the swap, with a fake sac.train that evaluates once and then fails."""
    from brax.training.agents.sac import train as sac

    from jaxrobo import deep
    from jaxrobo.deep.training import _train_sac

    original = acting.Evaluator
    seen = []

    def fake_train(progress_fn, **kwargs):
        acting.Evaluator.run_evaluation(None, "params-at-0", {})
        progress_fn(0, {})
        raise RuntimeError("trainer failed")

    monkeypatch.setattr(sac, "train", fake_train)
    with pytest.raises(RuntimeError, match="trainer failed"):
        _train_sac({"progress_fn": lambda step, m: None}, deep.SACConfig(),
                        lambda step, p: seen.append((step, p)))
    assert seen == [(0, "params-at-0")]
    assert acting.Evaluator is original


def test_evaluator_swap_guard_trips(monkeypatch):
    with pytest.warns(RuntimeWarning, match=r"brax 0\.99\.0 is outside"):
        with brax_compat.keep_evaluator_params("0.99.0") as hook:
            pass
    with pytest.raises(brax_compat.BraxCompatError, match=r"brax 0\.99\.0: sac\.train never handed"):
        hook.check()  # a trainer that no longer builds acting.Evaluator leaves no evaluations: said, not an IndexError

    class NotAnEvaluator:
        pass

    monkeypatch.setattr(acting, "Evaluator", NotAnEvaluator)
    with pytest.raises(brax_compat.BraxCompatError, match="has no run_evaluation"):
        with brax_compat.keep_evaluator_params():
            pass
    assert acting.Evaluator is NotAnEvaluator


def test_epoch_hook_wraps_only_training_epoch_and_is_undone(monkeypatch):
    """hook_epochs swaps the trainer module's ``jax`` for the block only, wraps the pmap of ``training_epoch`` (its
    key becomes jaxrobo's, its output state is kept, a restore replaces the first epoch's state) and nothing else."""
    import types

    import jax
    import jax.numpy as jnp

    module = types.SimpleNamespace(__name__="fake_trainer", jax=jax)
    seen = []
    state = None

    def training_epoch(state, key):
        return state + 1, key  # (the key as the "metrics": what the epoch was given)

    def reset(x):
        return x

    def keys(i, n):
        return jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), i), n)

    with brax_compat.hook_epochs(module, keys, first_epoch=3, restore=lambda fresh: (fresh[0] + 100,)) as hook:
        epoch = module.jax.pmap(training_epoch)
        other = module.jax.pmap(reset)
        assert module.jax.numpy is jnp  # everything else is JAX's own
        key = jax.random.split(jax.random.PRNGKey(7), 1)
        for start in (jnp.zeros((1,)), None):
            state, given = epoch(state if start is None else start, key)
            seen.append(np.asarray(given))
        assert np.asarray(other(jnp.ones((1,))))[0] == 1
    assert module.jax is jax
    assert float(state[0]) == 102 and hook.epochs_done == 5 and hook.calls == 2
    assert float(hook.states[0][0]) == 102
    expected = [np.asarray(jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), i), 1)) for i in (3, 4)]
    assert all(np.array_equal(a, b) for a, b in zip(seen, expected))  # not the key the trainer passed


def test_the_first_epoch_runs_the_program_of_every_later_one(caplog):
    """The trainer's first state comes from ``device_put_replicated`` (jaxrobo's replacement: a mesh of its own
    axis name) and every later one from the mapped epoch: the hook puts the first on the epoch's own sharding, so
    the epoch is lowered once, not once more for the first call (on an H200 the second lowering and compile of
    QuadcopterGotoTwist-v0's epoch cost 1.7 s of every run)."""
    import logging
    import types

    import jax

    module = types.SimpleNamespace(__name__="fake_trainer", jax=jax)

    def training_epoch(state, env, key):
        return state * 2.0 + jax.lax.pmean(env, "i"), env + 1.0, key

    keys = lambda i, n: jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), i), n)  # noqa: E731
    devices = jax.local_devices()[:1]
    state = brax_compat.device_put_replicated(np.ones(3, np.float32), devices)
    env = jax.pmap(lambda x: x, axis_name="i")(np.zeros((1, 3), np.float32))  # as Brax's pmapped reset gives it
    jax.config.update("jax_log_compiles", True)
    try:
        with caplog.at_level(logging.WARNING, logger="jax._src.dispatch"):
            with brax_compat.hook_epochs(module, keys) as hook:
                epoch = module.jax.pmap(training_epoch, axis_name="i", donate_argnums=(0, 1))
                for _ in range(3):
                    state, env, _ = epoch(state, env, jax.random.split(jax.random.PRNGKey(1), 1))
    finally:
        jax.config.update("jax_log_compiles", False)
    lowered = [r for r in caplog.records if "MLIR module conversion" in r.getMessage()
               and "jit(_fun)" in r.getMessage()]
    assert hook.calls == 3 and len(lowered) == 1, [r.getMessage() for r in lowered]
    assert np.asarray(state).tolist() == [[12.0, 12.0, 12.0]] and np.asarray(env).tolist() == [[3.0, 3.0, 3.0]]


def test_the_epochs_run_the_program_compile_epoch_gives():
    """``compile_epoch`` is asked once, with the first epoch's arguments (jaxrobo's key last) and the mapped
    epoch's donated positions; every epoch then runs what it returned, its arguments on the shardings it was
    compiled for. Where it returns None the mapped epoch runs."""
    import types

    import jax

    def training_epoch(state, key):
        return state + 1.0, key

    keys = lambda i, n: jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), i), n)  # noqa: E731
    asked = []

    def compile_epoch(mapped, args, donate):
        asked.append((len(args), donate))
        return jax.jit(mapped, donate_argnums=donate).lower(*args).compile()

    for make, expected in ((compile_epoch, [(2, (0,))]), (lambda *a: None, [])):
        asked.clear()
        module = types.SimpleNamespace(__name__="fake_trainer", jax=jax)
        state = brax_compat.device_put_replicated(np.zeros(2, np.float32), jax.local_devices()[:1])
        with brax_compat.hook_epochs(module, keys, compile_epoch=make) as hook:
            epoch = module.jax.pmap(training_epoch, axis_name="i", donate_argnums=0)
            for _ in range(3):
                state, _ = epoch(state, jax.random.split(jax.random.PRNGKey(1), 1))
        assert asked == expected and hook.calls == 3 and np.asarray(state).tolist() == [[3.0, 3.0]]


def test_epoch_hook_guard_trips():
    import types

    with pytest.raises(brax_compat.BraxCompatError, match="does not use the jax module"):
        with brax_compat.hook_epochs(types.SimpleNamespace(__name__="t"), lambda i, n: None):
            pass

    import jax

    with pytest.warns(RuntimeWarning, match=r"brax 0\.99\.0 is outside"):
        with brax_compat.hook_epochs(types.SimpleNamespace(__name__="t", jax=jax), lambda i, n: None,
                                     version="0.99.0") as hook:
            pass
    with pytest.raises(brax_compat.BraxCompatError, match="ran no jax.pmap-ed training_epoch"):
        hook.check()


@pytest.mark.parametrize("agent, parts, index", [("ppo", 3, 2), ("sac", 2, 1)])
def test_advance_epoch_keys_is_the_carry_of_the_epochs_scan(agent, parts, index):
    """The key an epoch's ``lax.scan`` carries after k training steps (PPO's ``training_step`` splits its key in
    three and carries the third, SAC's epoch splits in two and carries the second), per device; 0 steps: the keys
    themselves."""
    import jax

    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    expected = []
    for key in keys:
        for _ in range(5):
            key = jax.random.split(key, parts)[index]
        expected.append(np.asarray(key))
    assert np.array_equal(np.asarray(brax_compat.advance_epoch_keys(agent, keys, 5)), np.stack(expected))
    assert brax_compat.advance_epoch_keys(agent, keys, 0) is keys
