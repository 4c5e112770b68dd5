"""The host driver: one chunk loop (done test, stop hook, checkpoint cadence, time limit) for train and the sweep,
and the SIGINT/SIGTERM stop flag both command lines use."""
from __future__ import annotations

import signal

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.training import driver


def _loop(n_chunks=10, per_chunk=1, total=5, **kw):
    """A carry whose "episodes done" grows by ``per_chunk`` a chunk: nothing to compile."""
    calls = []

    def chunk(c):
        calls.append(int(c))
        return c + per_chunk

    read = lambda c: (jnp.asarray(c, jnp.float32), jnp.asarray(-1.0))  # noqa: E731
    run = driver.run_chunks(chunk, jnp.asarray(0), n_chunks, read=read, total=total, **kw)
    return run, calls


def test_runs_until_every_env_is_done_or_the_chunks_are_spent():
    seen = []
    run, calls = _loop(progress=lambda done, total, last: seen.append((done, total, last)))
    assert (run.chunks_done, run.done, run.stopped, int(run.carry)) == (5, 5.0, False, 5)
    assert seen == [(i, 5, -1.0) for i in range(1, 6)]
    run, _ = _loop(n_chunks=3)
    assert (run.chunks_done, run.done) == (3, 3.0)
    run, calls = _loop(start_chunk=8)  # a resumed carry counts the chunks it already ran
    assert (run.chunks_done, len(calls)) == (10, 2)
    run = driver.run_chunks(lambda c: c + 1, jnp.asarray(0), 4)  # nothing read back between chunks
    assert (run.chunks_done, run.done, int(run.carry)) == (4, None, 4)


def test_checkpoint_cadence_then_the_end_and_a_stop_save_once_more():
    saved = []
    run, _ = _loop(total=7, checkpoint=lambda c, n: saved.append((int(c), n)), checkpoint_every=2)
    assert saved == [(2, 2), (4, 4), (6, 6), (7, 7)] and run.chunks_done == 7  # the finished carry is saved
    saved.clear()
    run, _ = _loop(total=6, checkpoint=lambda c, n: saved.append((int(c), n)), checkpoint_every=2)
    assert saved == [(2, 2), (4, 4), (6, 6)]  # the cadence saved the last chunk: not twice
    saved.clear()
    run, calls = _loop(start_chunk=10, checkpoint=lambda c, n: saved.append((int(c), n)))
    assert calls == [] and saved == []  # a finished carry resumed runs nothing and is its checkpoint already
    run, _ = _loop(total=3, checkpoint=lambda c, n: saved.append((int(c), n)))
    assert saved == [(3, 3)]  # no cadence: saved once, at the end
    saved.clear()
    answers = iter([False, False, True])  # a stop request after two chunks
    run, calls = _loop(checkpoint=lambda c, n: saved.append((int(c), n)), should_stop=lambda: next(answers))
    assert run.stopped and run.chunks_done == 2 and saved == [(2, 2)]  # asked before each chunk, saved at the end
    run, calls = _loop(should_stop=lambda: True)
    assert run.stopped and run.chunks_done == 0 and calls == []


def test_max_seconds_ends_the_loop_after_at_least_one_chunk():
    run, calls = _loop(max_seconds=0.0)
    assert (run.chunks_done, run.stopped, len(calls)) == (1, False, 1)


@pytest.fixture
def python_sigint_handler():
    """Python's own SIGINT handler as the one from before, whatever this process inherited (a shell's background
    job starts with SIGINT ignored, and then a second SIGINT would meet that)."""
    inherited = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, inherited)


def test_stop_on_signal_sets_a_flag_then_quits_on_a_second_signal(python_sigint_handler):
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    noticed = []
    with driver.StopOnSignal(noticed.append, second="exit") as stop:
        assert not stop() and stop.name is None
        signal.raise_signal(signal.SIGTERM)
        assert stop() and stop.name == "SIGTERM" and noticed == [signal.SIGTERM]
        with pytest.raises(SystemExit) as exc:
            signal.raise_signal(signal.SIGINT)
        assert exc.value.code == 128 + signal.SIGINT
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    with driver.StopOnSignal() as stop:  # second="default": the next one meets the handler from before
        signal.raise_signal(signal.SIGINT)
        assert stop.signum == signal.SIGINT
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    with pytest.raises(ValueError, match="second="):
        driver.StopOnSignal(second="ignore")


def test_train_and_the_sweep_run_their_chunks_through_the_same_driver(monkeypatch):
    from jaxrobo.training import sweep
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    loops = []
    run_chunks = driver.run_chunks

    def spy(chunk, carry, n_chunks, **kw):
        run = run_chunks(chunk, carry, n_chunks, **kw)
        loops.append((np.shape(carry.episode), run.chunks_done))
        return run

    monkeypatch.setattr(driver, "run_chunks", spy)
    small = {"n_envs": 2, "nepisodes": 2, "nsteps": 10, "chunk_steps": 10, "backend": "analytic", "eval_episodes": 0}
    spec = resolve("CartPoleStayUp-v0", overrides=small)
    result = train(spec.env, spec.config, spec.agent_params)
    assert result.complete and loops == [((2,), result.chunks_done)]
    out = sweep.run_sweep("CartPoleStayUp-v0", [{"alpha": 0.1}, {"alpha": 0.5}], [0], overrides=small)
    assert len(out.rows) == 2 and len(loops) == 2 and loops[1][0] == (2, 2)  # rows × envs


def test_a_population_needs_its_rows_parameters_and_a_plan_of_one_device():
    import jax

    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    spec = resolve("CartPoleStayUp-v0", overrides={"n_envs": 2, "nepisodes": 2, "nsteps": 10, "backend": "analytic"})
    rows = driver.Population(np.stack([jax.random.key_data(jax.random.key(s)) for s in (0, 1)]), lambda *a: {})
    with pytest.raises(ValueError, match="rows' parameters"):
        train(spec.env, spec.config, population=rows)
    plan = ExecutionPlan.for_run(spec.env, spec.config).replace(devices=2)
    with pytest.raises(ValueError, match="devices=2"):
        train(spec.env, spec.config, spec.agent_params, spec.env.default_params, plan=plan, population=rows)


# The sizes of the tiny runs of tests/test_goto_v2.py and tests/test_arm_reach.py (their compiled chunks are reused);
# a wide arrival radius (a traced parameter: the same programs), so that some episodes arrive and some do not.
@pytest.mark.parametrize("env_id, overrides", [
    # snapshots=0: the final table's choice (its own flights, before the evaluation) is tested in test_goto_v2
    ("QuadcopterGoto-v2", {"nsteps": 12, "chunk_steps": 12, "eval_episodes": 4, "goal_tolerance": 5.0,
                           "snapshots": 0}),
    ("ArmReach-v0", {"nsteps": 10, "chunk_steps": 10, "eval_episodes": 8, "goal_tolerance": 0.3})])
@pytest.mark.slow
def test_the_greedy_evaluation_flies_once_and_counts_arrivals_as_a_second_flight_would(env_id, overrides,
                                                                                       monkeypatch):
    """The arrivals come from the evaluation's own flight: one flight traced, and the same flags a second flight
    of the same tables on the same keys (one scan, how they used to be counted, the oracle here) finds."""
    import jax

    from jaxrobo.task import rollout
    from jaxrobo.training.run import resolve
    from jaxrobo.tabular.discretise import make_discretiser_for
    from jaxrobo.training.train import train

    spec = resolve(env_id, overrides={"n_envs": 2, "nepisodes": 2, "eval_envs": 1, **overrides})
    env, config = spec.env, spec.config
    flown, started = rollout.rollout, rollout.rollout_start
    flights = []
    # The evaluation flies in segments (progress between them): a flight is one rollout_start.
    monkeypatch.setattr(rollout, "rollout_start", lambda *a, **kw: flights.append(a[2]) or started(*a, **kw))
    monkeypatch.setattr(rollout, "rollout", lambda *a, **kw: flights.append(a[3]) or flown(*a, **kw))
    res = train(env, config, spec.agent_params)
    assert flights == [config.eval_episodes]  # one table evaluated: one flight, none more for the arrivals

    disc, params, horizon = make_discretiser_for(env, config), env.default_params, env.spec.max_episode_steps

    def second_flight(k, q):
        out = flown(env, rollout.greedy_policy(q, disc), k, config.eval_episodes, horizon, params)
        return out["last"].task.arrived, out["return"]

    keys = jax.random.split(jax.random.fold_in(jax.random.key(config.seed), 1), 1)
    arrived, returns = (np.asarray(x) for x in jax.jit(jax.vmap(second_flight))(keys, res.q[:1]))
    np.testing.assert_array_equal(returns, res.eval_returns)  # the same episodes
    assert res.eval_success.dtype == bool and 0.0 < arrived.mean() < 1.0
    np.testing.assert_array_equal(res.eval_success, arrived)
    assert res.summary()["eval_success_rate"] == float(arrived.mean())


def _compiles(caplog, fn):
    """``fn()``'s result and the names of the programs JAX compiled while it ran (its compile log)."""
    import logging

    import jax

    caplog.clear()
    with caplog.at_level(logging.WARNING), jax.log_compiles():
        out = fn()
    return out, [r.getMessage().split(" ")[1] for r in caplog.records if r.getMessage().startswith("Compiling")]


def test_small_programs_compile_once_from_their_shapes_whichever_asks_first(caplog):
    """:class:`driver.PerShape`: prepared ahead from abstract values or called first with arrays, one program per
    shapes (the same one either way: lowered from the shapes), its values those of the eager operations; and a
    :class:`driver.CompilingInThread` returns what the caller's own compile would."""
    import jax

    x, x1, key, x6 = jnp.arange(4.0), jnp.arange(1.0, 5.0), jax.random.key(7), jnp.arange(6.0)
    for scale, prepare_first in ((2.0, True), (3.0, False)):  # another scale: another program, not JAX's kept one
        def inputs(x, key, n):
            return x * scale, jax.random.split(jax.random.fold_in(key, n), 3)

        f = driver.PerShape(inputs)
        abstract = (jax.ShapeDtypeStruct(x.shape, x.dtype), jax.ShapeDtypeStruct(key.shape, key.dtype),
                    jax.ShapeDtypeStruct((), np.int32))
        _, compiled = _compiles(caplog, lambda: (f.prepare(*abstract) if prepare_first else None,
                                                 f(x, key, np.int32(5)), f(x1, key, np.int32(5))))
        assert compiled == ["jit(inputs)"]
        got = f(x, key, np.int32(5))
        assert np.array_equal(got[0], x * scale)
        assert np.array_equal(jax.random.key_data(got[1]),
                              jax.random.key_data(jax.random.split(jax.random.fold_in(key, 5), 3)))
        _, compiled = _compiles(caplog, lambda: f(x6, key, np.int32(5)))  # another shape: its own program
        assert compiled == ["jit(inputs)"]
    ahead = driver.CompilingInThread(jax.jit(lambda v: v + 1.0).lower(x))
    assert np.array_equal(ahead(x), x1) and ahead.wait() is ahead.wait()


def test_a_compile_that_fails_in_its_thread_fails_again_where_the_caller_sees_it():
    """The thread keeps nothing of a failed compile; waiting compiles again in the caller's thread, which raises."""
    attempts = []

    class Failing:
        def compile(self):
            attempts.append(1)
            raise RuntimeError("XLA says no")

    ahead = driver.CompilingInThread(Failing())
    with pytest.raises(RuntimeError, match="XLA says no"):
        ahead.wait()
    assert len(attempts) == 2 and not ahead.thread.is_alive()


@pytest.mark.parametrize("env_id", ["CartPoleStayUp-v0", "QuadcopterGoto-v2", "ArmReach-v0"])
def test_a_runs_bounds_and_discretiser_are_built_on_the_host(env_id, caplog):
    """The task's state bounds (numpy float32) and the discretiser built from them compile no program: each
    eager ``jax.numpy`` operation there was one more program a GPU compiled before the run started."""
    from jaxrobo.tabular.discretise import make_discretiser_for
    from jaxrobo.training.run import resolve

    spec = resolve(env_id)
    (low, high), compiled = _compiles(caplog, spec.env.state_bounds)
    assert compiled == [] and low.dtype == high.dtype == np.float32 and isinstance(low, np.ndarray)
    assert np.all(low < high)
    disc, compiled = _compiles(caplog, lambda: make_discretiser_for(spec.env, spec.config))
    assert compiled == [] and disc.n_states > 1


def test_the_closing_checkpoint_copies_the_carry_after_the_evaluation_and_a_failed_one_still_saves():
    """:class:`~jaxrobo.training.checkpoint.SaveInThread` held by the driver: the save after the last chunk is
    handed over before the evaluation but reads the carry only after the evaluation's last segment (their reads
    from the device share one queue); an evaluation that fails releases it, and the finished carry is saved."""
    import threading
    import time

    from jaxrobo.training import checkpoint
    from jaxrobo.training.callbacks import Callback
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    spec = resolve("CartPoleStayUp-v0", overrides={"env.backend": "analytic", "n_envs": 4, "nepisodes": 3,
                                                    "nsteps": 20, "chunk_steps": 20, "eval_episodes": 2,
                                                    "eval_envs": 2, "stop_at_target": False})
    events, lock = [], threading.Lock()

    def save(carry, chunks_done):
        with lock:
            events.append(("save", chunks_done, int(np.asarray(carry.episode).min())))

    class Segments(Callback):
        def __init__(self, fail=False):
            self.fail = fail

        def on_evaluation(self, progress):
            with lock:
                events.append(("segment",))
            if self.fail:
                raise RuntimeError("the evaluation broke")

    saves = checkpoint.SaveInThread(save)
    saves.HOLD_SECONDS = 120.0  # were it never released, the save would come two minutes late
    t0 = time.perf_counter()
    result = train(spec.env, spec.config, spec.agent_params, callbacks=[Segments()], checkpoint=saves)
    saves.wait()
    assert time.perf_counter() - t0 < saves.HOLD_SECONDS
    kinds = [e[0] for e in events]
    assert result.complete and kinds.count("save") == 1 and kinds[-1] == "save" and "segment" in kinds
    assert events[-1][1:] == (result.chunks_done, 3)  # the finished carry
    events.clear()
    saves = checkpoint.SaveInThread(save)
    saves.HOLD_SECONDS = 120.0
    with pytest.raises(RuntimeError, match="the evaluation broke"):
        train(spec.env, spec.config, spec.agent_params, callbacks=[Segments(fail=True)], checkpoint=saves)
    saves.wait()
    assert [e[0] for e in events] == ["segment", "save"] and events[-1][2] == 3
