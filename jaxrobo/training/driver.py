"""The host driver: compile a training chunk once, then run it chunk after chunk from a carry.

One loop serves every caller that trains: :func:`jaxrobo.training.train.train` (``jaxrobo train``, and the sweep's
groups as a :class:`Population`: a chunk vmapped or sharded over rows, :func:`run_population`) and the benchmarks.
The chunk is traced and compiled under the run's execution plan (:func:`compile_under`, :func:`compiled_chunk`); the
loop (:func:`run_chunks`) only dispatches compiled chunks and, between them, reads two numbers (fewest episodes done,
mean last return) for the done test and the progress bar, so the hot loop never syncs with the host inside a
chunk. Between chunks it asks a stop hook (``should_stop``: a chunk boundary is the only place a run stops) and
hands the carry to a checkpoint hook at its cadence (every N chunks and/or every T seconds), and at the end.

:func:`run_training` is a whole training run: compile, loop from a fresh or saved carry, greedy evaluation at the
end (:func:`evaluate_tables`, whose one flight also counts the arrivals of a task whose target is a success
rate), a :class:`~jaxrobo.training.summary.TrainResult`; :func:`run_population` is a whole training of a
:class:`Population`'s rows (compiled by :func:`compiled_population`), a :class:`PopulationResult`.
:class:`StopOnSignal` turns SIGINT / SIGTERM into a stop request for both command lines (``jaxrobo train``,
``jaxrobo sweep``); the library itself installs no signal handlers.

Public surface: :func:`compile_under`, :func:`compiled_chunk`, :func:`compiled_progress`, :func:`run_chunks` and
its :class:`ChunkRun` and :class:`Progress`, :func:`run_training`, :class:`Population`, :func:`compiled_population`,
:func:`run_population` and its :class:`PopulationResult`, :func:`evaluate_tables` (flown in segments by
:func:`fly`, reporting :class:`EvalProgress`; its pieces :func:`evaluated_tables`, :func:`evaluation_keys`,
:func:`table_figures` and :func:`choose_table`, which the learning benchmarks judge runs by),
:class:`StopOnSignal`, the hook types :data:`ProgressFn` and :data:`CheckpointFn`. Names with a leading underscore
are private.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import threading
import time
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.tabular import learner as tabular
from jaxrobo.tabular.learner import AgentParams
from jaxrobo.training import budget
from jaxrobo.training import checkpoint as checkpoint_io
from jaxrobo.training import nonzero_copy, record_parts
from jaxrobo.speed import locked_copy, reuse, sharding
from jaxrobo.speed.plan import ExecutionPlan, physics_kernel
from jaxrobo.core import rng
from jaxrobo.core.precision import check_precision
from jaxrobo.task.env import ranking
from jaxrobo.training.summary import TrainResult
from jaxrobo.training.trainer import Runner, Trainer, progress_stats

@dataclasses.dataclass(frozen=True)
class Progress:
    """Where a run stands after a chunk: what every progress line, bar and live TensorBoard scalar reads (one
    definition of each number).

    ``done`` / ``total`` count the run's budget in ``unit`` (:attr:`jaxrobo.training.trainer.Trainer.budget_total`:
    episodes per env, steps per env, or episodes of the whole run); ``last_return`` is the mean over envs of each
    env's last recorded episode's return; ``useful_steps`` the env steps that counted towards the budget (an env
    past its budget, or past its episodes, still occupies its slot: it is not useful); ``slot_steps`` the steps
    the batch ran (chunks × chunk steps × envs × rows) since the carry's first chunk; ``seconds`` the wall time of
    this loop, compile excluded."""

    chunks_done: int
    n_chunks: int
    done: int
    total: int
    unit: str
    last_return: float
    useful_steps: float
    slot_steps: float
    seconds: float
    #: ``done`` and ``useful_steps`` of the carry this loop started from (a resumed carry's are not 0): the rates
    #: count this loop's work only.
    done_before: int = 0
    useful_before: float = 0.0

    @property
    def useful_share(self) -> float:
        """Useful env steps / env slots stepped (1.0: every slot of every step did work that counts)."""
        return self.useful_steps / self.slot_steps if self.slot_steps else 0.0

    @property
    def steps_per_second(self) -> float:
        """Useful env steps this loop ran per second of it (a resumed carry's earlier steps left out)."""
        return (self.useful_steps - self.useful_before) / self.seconds if self.seconds > 0 else 0.0

    @property
    def eta(self) -> float:
        """Seconds left at this loop's pace of the budget (NaN before any of it was done)."""
        rate = (self.done - self.done_before) / self.seconds if self.seconds > 0 else 0.0
        return max(self.total - self.done, 0) / rate if rate > 0 else float("nan")


#: ``progress(Progress)`` after each chunk; a callable of three positional parameters is called the earlier way,
#: ``progress(done, total, mean_last_return)``.
ProgressFn = Callable[..., None]
#: ``checkpoint(carry, chunks_done)``, called at the checkpoint cadence and when the run stops early. One with a
#: ``last`` method of the same signature (:class:`jaxrobo.training.checkpoint.SaveInThread`) gets the save after
#: the last chunk through it: no chunk follows (none reuses the carry's buffers), so it may go on reading the carry
#: once it has returned.
CheckpointFn = Callable[[Any, int], None]


# ---- compiling ---------------------------------------------------------------------------------------------------
def compile_under(plan: ExecutionPlan, jitted: Any, *args: Any) -> Callable:
    """``jitted`` (a ``jax.jit``-wrapped function) lowered for ``args`` and compiled, traced under ``plan``.

    Traced afresh in every process and every call, so a run executes the code as it is now in this process (a
    patched physics step, another plan). A second start of the same configuration still skips XLA: the
    persistent compilation cache (:mod:`jaxrobo.speed.cache`) is keyed on the lowered module, so it serves the
    executable only when the traced program is the same. (A run's init, chunk and evaluation on one device go
    through :func:`jaxrobo.speed.reuse.compile_reusing`, which with the plan's ``reuse_traces`` skips the trace.)"""
    with plan.tracing():
        return jitted.lower(*args).compile()


def env_mesh(trainer: Trainer) -> Any:
    """The 1-D mesh the run's envs are split over (``plan.devices`` of JAX's devices, every process's under
    ``jax.distributed``), or None for one device."""
    from jaxrobo.speed import sharding

    d = trainer.plan.devices
    return None if d == 1 else sharding.make_mesh(jax.devices()[:d])


def compiled_init(trainer: Trainer, key: jax.Array, agent_params: AgentParams, env_params: Any) -> Callable:
    """``trainer.init`` compiled under the plan, its carry split over the plan's devices (:func:`env_mesh`)."""
    mesh = env_mesh(trainer)
    if mesh is None and trainer.plan.reuse_traces:  # a trace kept by an earlier process, read back
        # (trainer.jitted_init: where the checkpoint's template traced it, the export takes that trace)
        return reuse.compile_reusing(trainer.plan, "init", trainer.jitted_init, (key, agent_params, env_params),
                                     trainer)
    if mesh is None:
        jitted = trainer.jitted_init  # the trace the checkpoint's template made, if it made one
    else:
        out = jax.eval_shape(trainer.init, key, agent_params, env_params)
        # (spmd_options: on CPUs the passes that round a program for several devices otherwise than one device's)
        jitted = jax.jit(trainer.init, out_shardings=_carry_shardings(out, mesh, trainer.config.n_envs),
                         compiler_options=sharding.spmd_options(trainer.plan.xla_options, mesh))
    return compile_under(trainer.plan, jitted, key, agent_params, env_params)


def compiled_chunk(trainer: Trainer, runner: Runner, agent_params: AgentParams, env_params: Any, *,
                   in_thread: bool = False) -> Callable:
    """``trainer.run_chunk`` compiled for ``runner`` under the trainer's plan (its compiler options, its
    trace-time choices), the carry donated: ``runner = chunk(runner, agent_params, env_params)``. Over several
    devices (``plan.devices``) the carry's env axis is split over them: XLA partitions the chunk (a shared table's
    update and a run-wide episode count become reductions across devices), and the Pallas chunk kernel, which
    XLA cannot partition, runs on each device's envs through ``shard_map`` (its envs are independent).

    ``in_thread``: traced here, compiled by XLA in a thread (a :class:`CompilingInThread`, which waits for it when
    first called), so that the caller traces its other programs during the chunk's compile, a default GPU run's
    longest (6 s of the arm's cold start on an H200)."""
    from jaxrobo.speed import sharding

    plan = trainer.plan
    mesh = env_mesh(trainer)
    if mesh is None:
        lowered = reuse.lower_reusing(plan, "chunk", trainer.run_chunk, (runner, agent_params, env_params), trainer,
                                      donate=(0,))
        return CompilingInThread(lowered) if in_thread else lowered.compile()
    n = trainer.config.n_envs
    carry = _carry_shardings(runner, mesh, n)
    rep = sharding.replicated(mesh)
    params = (jax.tree.map(lambda _: rep, agent_params), jax.tree.map(lambda _: rep, env_params))
    fn = trainer.run_chunk
    if per_device_chunk(trainer, mesh):
        from jax.sharding import PartitionSpec as P

        specs = jax.tree.map(lambda s: s.spec, carry)
        local = trainer.share(n // plan.devices, plan.replace(devices=1), devices=1)  # one device's envs
        steps = jax.shard_map(local._run_steps, mesh=mesh, in_specs=(specs, P(), P()),
                              out_specs=specs, check_vma=False)
        # The snapshots follow the whole run's progress, so they are kept outside the per-device programs.
        fn = lambda r, ap, ep: trainer.keep_snapshots(steps(r, ap, ep))  # noqa: E731
    # spmd_options: compiled as a sweep's rows are, so that each device's envs round as one device's do (on 4 forced
    # CPU devices Goto-v2's per-env returns otherwise moved in their last bits from the first episode on).
    jitted = jax.jit(fn, donate_argnums=0, compiler_options=sharding.spmd_options(plan.xla_options, mesh),
                     in_shardings=(carry,) + params, out_shardings=carry)
    if not in_thread:
        return compile_under(plan, jitted, runner, agent_params, env_params)
    with plan.tracing():
        return CompilingInThread(jitted.lower(runner, agent_params, env_params))


def per_device_chunk(trainer: Trainer, mesh: Any) -> bool:
    """Whether a run split over ``mesh`` steps each device's envs with the one-device program (``shard_map``)
    rather than a chunk XLA partitions: always for the Pallas chunk kernel, which XLA cannot partition; and on
    GPUs for envs that are independent (per-env tables, a budget per env), since there the partitioned program
    rounded QuadcopterGoto-v2's step otherwise than one GPU's (device_splits.json), while one GPU's program
    rounds alike whatever its batch (``env_group``). On CPUs the partitioned program, compiled without the CSE
    passes, is the one that matches: XLA's CPU code rounds the quadcopter's step by the batch it is given."""
    if trainer.plan.fused == "pallas" and not physics_kernel(trainer.env):
        return True
    independent = not trainer.config.shared_table and trainer.budget != "run_episodes"
    return independent and any(d.platform != "cpu" for d in mesh.devices.flat)


class CompilingInThread:
    """A lowered program (``jax.stages.Lowered``) whose XLA compile runs in a thread: XLA holds no Python lock
    while it compiles, so the caller traces its next programs meanwhile. Calling it (or :meth:`wait`) waits for
    the compile; a compile that failed in the thread runs again in the caller's, where its error is raised."""

    def __init__(self, lowered: Any) -> None:
        self.lowered, self._done = lowered, []
        self.thread = _in_thread(self._done, lowered.compile)

    def wait(self) -> Callable:
        """The compiled program, once compiled."""
        if not self._done:
            self.thread.join()
            if not self._done:
                self._done.append(self.lowered.compile())
        return self._done[0]

    def __call__(self, *args: Any) -> Any:
        return self.wait()(*args)


def _carry_shardings(carry: Runner, mesh: Any, n_envs: int) -> Any:
    """The carry's shardings over ``mesh``: the env axis split, the rest replicated; the snapshots (one run's
    tables, whose leading axis may happen to have ``n_envs`` entries) replicated as the shared table is."""
    from jaxrobo.speed import sharding

    out = sharding.shardings_like(carry, mesh, n_envs)
    return out if carry.snapshots is None else out.replace(snapshots=sharding.replicated(mesh))


def compiled_progress(carry: Runner, trainer: Trainer | None = None, *, in_thread: bool = False) -> Callable:
    """:meth:`jaxrobo.training.trainer.Trainer.progress` (without a trainer: the episode budget's
    :func:`~jaxrobo.training.trainer.progress_stats`) compiled for ``carry`` (one run's, or a sweep's rows);
    ``in_thread``: by XLA in a thread (a :class:`CompilingInThread`)."""
    lowered = jax.jit(progress_stats if trainer is None else trainer.progress).lower(carry)
    return CompilingInThread(lowered) if in_thread else lowered.compile()


def _caller_of(progress: ProgressFn | None) -> Callable[[Progress], None] | None:
    """``progress`` as a function of a :class:`Progress`: an earlier three-parameter callback gets
    ``(done, total, last_return)``."""
    if progress is None:
        return None
    import inspect

    try:
        params = [p for p in inspect.signature(progress).parameters.values()
                  if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty]
    except (TypeError, ValueError):
        params = []
    if len(params) == 3:
        return lambda p: progress(p.done, p.total, p.last_return)
    return progress


def host_get(tree: Any) -> Any:
    """Device arrays → host numpy, whole: :func:`jaxrobo.speed.locked_copy.get` in one process, every process's shards
    gathered under ``jax.distributed`` (a collective: every process calls it at the same point)."""
    if jax.process_count() > 1:
        from jaxrobo.speed import sharding

        return sharding.gather(tree)
    return locked_copy.get(tree)


# ---- the loop ----------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class ChunkRun:
    """What :func:`run_chunks` ends with."""

    carry: Any
    chunks_done: int  # counted from the carry's start (``start_chunk``)
    done: float | None  # fewest episodes done by any env (None without a ``read``)
    stopped: bool  # ``should_stop`` ended the loop early
    seconds: float  # wall time of the loop, the last chunk waited for
    #: The chunk count at which ``check`` said the run is done (the learning target met), else None.
    checked_done_at: int | None = None
    check_seconds: float = 0.0  # wall time of the ``check`` calls, inside ``seconds``
    save_seconds: float = 0.0  # wall time of the checkpoint saved after the loop (outside ``seconds``)


def run_chunks(chunk: Callable[[Any], Any], carry: Any, n_chunks: int, *, start_chunk: int = 0,
               read: Callable[[Any], Any] | None = None, total: int | None = None,
               progress: ProgressFn | None = None, should_stop: Callable[[], bool] | None = None,
               checkpoint: CheckpointFn | None = None, checkpoint_every: int = 0,
               checkpoint_seconds: float | None = None, max_seconds: float | None = None,
               unit: str = "episodes", slots_per_chunk: float = 0.0, save_at_end: bool = True,
               check: Callable[[Any, int], bool] | None = None, check_every: int = 0) -> ChunkRun:
    """Run ``carry = chunk(carry)`` until ``n_chunks`` chunks are done (counting the ``start_chunk`` the carry
    has already run) or every env has done ``total`` episodes.

    ``read(carry) -> (done, mean_last_return[, useful_steps])`` (e.g. :func:`compiled_progress`) is read before
    the loop and after each chunk, for the done test (``done >= total``, in ``unit``) and ``progress``, which gets
    a :class:`Progress` (``slots_per_chunk``: env slots one chunk steps, for its useful share); without ``read``
    the loop runs its chunks without reading anything back (the chunks are dispatched back to back). ``should_stop()``
    is asked before each chunk: True ends the loop (``stopped``) after the chunk in flight. ``max_seconds`` ends
    it (not ``stopped``) before a chunk once that much time has passed, at least one chunk run.
    ``checkpoint(carry, chunks_done)`` is called every ``checkpoint_every`` chunks and/or at the first chunk
    boundary ``checkpoint_seconds`` after the last call (neither: none on the way), and once more with the carry
    the loop ends with (stopped, finished or out of time) unless that one was just saved: what the caller does
    after the loop (evaluating, writing results and plots) may fail, and a resume then starts from the finished
    carry instead of running chunks again. ``save_at_end=False`` leaves that last call to a stopped loop (a
    sweep's group saves its metrics, not its carry, once it has run: :mod:`jaxrobo.training.sweep.running`).
    ``check(carry, chunks_done) -> bool`` is asked after every ``check_every``-th chunk (counted from the run's
    start, so a resumed loop asks where the uninterrupted one did; not after the last chunk): True ends the loop
    there, finished (``checked_done_at``), as the learning-target stop does."""
    done = last = None
    report = _caller_of(progress)
    before: list[float] = [0.0, 0.0, 0.0]
    if read is not None:
        before = [float(x) for x in host_get(read(carry))] + [0.0]
        done = before[0]
        if before[2] != before[2]:  # a read without useful steps (NaN): nothing to subtract
            before[2] = 0.0

    def finished(chunks_done: int) -> bool:
        return chunks_done >= n_chunks or (done is not None and total is not None and done >= total)

    t0 = last_saved = time.perf_counter()
    chunks_done, stopped = start_chunk, False
    saved_at = None  # the chunk count of the last checkpoint written by this loop
    checked_at, check_seconds = None, 0.0
    if check is not None and check_every > 0 and start_chunk > 0 and start_chunk % check_every == 0 \
            and not finished(start_chunk):
        # A carry saved at a check point (a run stopped during its evaluation, after the target was met): the same
        # check, on the same carry and keys, says again what it said there.
        t_check = time.perf_counter()
        checked_at = start_chunk if check(carry, start_chunk) else None
        check_seconds += time.perf_counter() - t_check
    while checked_at is None and not finished(chunks_done):
        if should_stop is not None and should_stop():
            stopped = True
            break
        if max_seconds is not None and sharding.largest(
                chunks_done > start_chunk and time.perf_counter() - t0 > max_seconds)[0]:
            break  # every process's clock asked: out of time in one, the processes all stop here
        carry = chunk(carry)
        chunks_done += 1
        if read is not None:
            values = [float(x) for x in host_get(read(carry))]
            done, last = values[0], values[1]
            if report is not None:
                report(Progress(chunks_done, n_chunks, int(done), total if total is not None else n_chunks, unit,
                                last, values[2] if len(values) > 2 else float("nan"),
                                chunks_done * slots_per_chunk, time.perf_counter() - t0, int(before[0]),
                                before[2] if len(values) > 2 else 0.0))
        if check is not None and check_every > 0 and chunks_done % check_every == 0 and not finished(chunks_done):
            t_check = time.perf_counter()
            met = check(carry, chunks_done)
            check_seconds += time.perf_counter() - t_check
            if met:
                checked_at = chunks_done
        # A save by the clock is due where any process's clock says so: the save is a collective under
        # jax.distributed (its carry is gathered), so the processes save at the same chunks or none does.
        due = (checkpoint_every > 0 and chunks_done % checkpoint_every == 0) or (
            checkpoint_seconds is not None and checkpoint is not None
            and bool(sharding.largest(time.perf_counter() - last_saved >= checkpoint_seconds)[0]))
        if checkpoint is not None and due:
            checkpoint(carry, chunks_done)
            saved_at, last_saved = chunks_done, time.perf_counter()
        if checked_at is not None:
            break
    jax.block_until_ready(carry)
    seconds = time.perf_counter() - t0
    # A resumed carry that ran no chunk is its checkpoint already, unless a stop asks for one explicitly.
    unsaved = saved_at != chunks_done and (chunks_done > start_chunk or stopped)
    t_save = time.perf_counter()
    if checkpoint is not None and unsaved and (save_at_end or stopped):
        getattr(checkpoint, "last", checkpoint)(carry, chunks_done)
    return ChunkRun(carry, chunks_done, done, stopped, seconds, checked_at, check_seconds,
                    time.perf_counter() - t_save)


# ---- a whole training run ----------------------------------------------------------------------------------------
def run_training(trainer: Trainer, agent_params: AgentParams | None = None, env_params: Any = None,
                 progress: ProgressFn | None = None, *, initial: Runner | None = None, start_chunk: int = 0,
                 checkpoint: CheckpointFn | None = None, checkpoint_every: int = 0,
                 checkpoint_seconds: float | None = None,
                 should_stop: Callable[[], bool] | None = None,
                 announce: Callable[[str], None] | None = None,
                 eval_progress: Callable[[EvalProgress], None] | None = None) -> TrainResult:
    """Train with ``trainer`` from ``initial`` (a carry after ``start_chunk`` chunks; default: a fresh
    ``trainer.init``), then evaluate (unless stopped): the body of :func:`jaxrobo.training.train.train`, which runs it
    inside the trainer's plan's tracing block. The hooks are :func:`run_chunks`'s; ``announce(line)`` is told when
    the evaluation starts, ``eval_progress`` after each segment of it (:func:`evaluate_tables`)."""
    env, config = trainer.env, trainer.config
    check_precision(env.name)  # x64 may have been switched on since the env was built; nothing is traced yet
    agent_params = agent_params or AgentParams()
    env_params = env.default_params if env_params is None else env_params
    # The CLI checked this in ``run.resolve``; a Python caller gets the same refusal before anything compiles.
    budget.check_memory(env, config, trainer.disc.n_states, where=env.name)
    key = rng.seed_key(config.seed)  # jax.random.key's key, no program compiled for it
    t0 = time.perf_counter()
    check_every, checks = trainer.target_every(), []
    # The flights' programs compile ahead where they are one device's (Flights: a split run's too, in one process).
    prepare = bool(check_every or config.eval_episodes) and (trainer.plan.devices == 1 or jax.process_count() == 1)
    # See ExecutionPlan: beside the chunk's compile, or after it (a split run's: after it).
    beside = prepare and trainer.plan.compile_beside and trainer.plan.devices == 1
    first: list[Callable] = []  # the first carry's compiled program, where a thread compiles it
    compiling_init = None
    if initial is not None:
        # Placed as a fresh carry is (its envs split over the plan's devices): the programs compiled from the carry
        # below (the chunk, the progress read) then take the carry every chunk returns.
        mesh = env_mesh(trainer)
        runner = initial if mesh is None else jax.device_put(
            initial, _carry_shardings(initial, mesh, trainer.config.n_envs))
    elif beside:  # the first carry's program compiles in a thread; the others compile from the carry's shapes
        from jaxrobo.training.checkpoint import carry_template

        runner = carry_template(trainer, agent_params, env_params)  # traced once here, or read from a kept trace
        compiling_init = _in_thread(first, compiled_init, trainer, key, agent_params, env_params)
    else:
        runner = compiled_init(trainer, key, agent_params, env_params)(key, agent_params, env_params)
    # Read before the first chunk takes the carry's buffers: a resumed run's steps/s counts this process's steps.
    restored = 0 if initial is None else int(np.asarray(host_get(initial.env_steps), np.int64).sum())
    flights = Flights(trainer, env_params)
    check = target_check(trainer, flights, key, checks) if check_every else None
    threads = [] if compiling_init is None else [compiling_init]  # joined however the block ends
    if trainer.plan.devices == 1 and jax.process_count() == 1:  # the large tables' copy at the end, beside the rest
        threads += nonzero_copy.prepare(runner.agent.q)
    with _joined(threads), _saved_after_evaluation(checkpoint, config.eval_episodes > 0):
        # Beside: the chunk is traced first (its XLA compile is the longest), then compiles in a thread while the
        # evaluation's programs are traced and compiled in another.
        chunk = compiled_chunk(trainer, runner, agent_params, env_params, in_thread=beside)
        if beside:
            threads.append(chunk.thread)
        stats = compiled_progress(runner, trainer, in_thread=beside)
        if beside:
            threads += [stats.thread, *prepare_evaluation(trainer, flights, runner, key)]
        if compiling_init is not None:
            compiling_init.join()
            if not first:  # the thread failed: compile here, where the caller sees the error
                first.append(compiled_init(trainer, key, agent_params, env_params))
            runner = first[0](key, agent_params, env_params)
        if prepare and not beside:  # compiled while the first chunks train
            threads += prepare_evaluation(trainer, flights, runner, key)
        if beside:
            chunk, stats = chunk.wait(), stats.wait()
        jax.block_until_ready(runner)
        compile_seconds = time.perf_counter() - t0
        parts_program = None
        if record_parts.wanted(*runner.returns.shape, config.nsteps):  # compiled while the run trains
            parts_program = record_parts.Prepared(runner.returns, runner.lengths, runner.episode,
                                                  higher=ranking(getattr(env, "learning_target", None)).higher)
            threads.append(parts_program.thread)

        total, unit = trainer.budget_total
        loop = run_chunks(lambda r: chunk(r, agent_params, env_params), runner, trainer.max_chunks(),
                          start_chunk=start_chunk, read=stats, total=total, progress=progress,
                          should_stop=should_stop, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                          checkpoint_seconds=checkpoint_seconds, unit=unit,
                          slots_per_chunk=float(config.chunk_steps) * config.n_envs, check=check,
                          check_every=check_every)
        runner = loop.carry
        eval_returns = eval_lengths = selected = eval_success = None
        t_eval = time.perf_counter()
        final_choice = None
        if not loop.stopped and runner.snapshots is not None and loop.checked_done_at is None:
            # A stopped run keeps its carry as it is: the resumed run chooses once it has finished. A run that met its
            # target keeps the table that met it (the snapshots lie at shares of a budget it did not run).
            runner, choice = jax.jit(trainer.final_table)(runner, key, env_params)
            final_choice = int(choice)
        stopped = loop.stopped
        if config.eval_episodes > 0 and not stopped:
            if announce is not None:  # the evaluation compiles and flies for a while after the bar's 100 %
                horizon = trainer.env.spec.max_episode_steps if trainer.env.spec else config.nsteps
                announce(f"evaluating {evaluated_tables(config)} table(s) × {config.eval_episodes} greedy "
                         f"episodes ≤ {horizon} steps (compile, then fly)")

            def segment(p: EvalProgress) -> None:  # a stop asked for during the evaluation ends it after a segment
                if eval_progress is not None:
                    eval_progress(p)
                if should_stop is not None and should_stop():
                    raise _EvaluationStopped

            try:
                eval_returns, eval_lengths, selected, eval_success = evaluate_tables(trainer, runner, key, env_params,
                                                                                     segment, flights)
            except _EvaluationStopped:
                # The training is finished (and checkpointed, where the caller saves one): the run stops as an
                # interrupted one after its last chunk; resuming it evaluates and writes the results, training nothing.
                stopped = True
                eval_returns = eval_lengths = selected = eval_success = None
                if announce is not None:
                    announce("stopped during the evaluation: the finished training is kept"
                             + (" (its checkpoint is saved); resuming evaluates and writes the results"
                                if checkpoint is not None else ""))
        eval_seconds = time.perf_counter() - t_eval

    # The records cross cut to their written columns, the tables as their nonzero entries (as the closing
    # checkpoint copies them: their bytes cross once), and get their zeros back here; the tables only where read.
    t_copy = time.perf_counter()
    rest = checkpoint_io.cut_records(runner.replace(key=None, env_state=None, agent=runner.agent.replace(q=None)))
    # The figures' and statistics' parts, where the records are, computed and copied in a thread while the records
    # cross (a stopped run writes neither); started once the records' cut is dispatched, which would otherwise wait
    # behind the program's first call (1.2 s at 1 M envs on an H200: it allocates its temporaries).
    parts = None if parts_program is None or stopped else parts_program.start(runner.returns, runner.lengths,
                                                                               runner.episode)
    host = host_get(rest)
    host = host.replace(**{name: checkpoint_io.pad_columns(np.asarray(getattr(host, name)), runner.returns.shape[1])
                           for name in ("returns", "lengths", "terminated")})
    q = host_get(runner.agent.q) if jax.process_count() > 1 else nonzero_copy.host_copy(runner.agent.q)
    parts = None if parts is None else parts.result()
    copy_seconds = time.perf_counter() - t_copy
    return TrainResult(
        env_id=env.name, config=config, agent_params=agent_params,
        returns=np.asarray(host.returns), lengths=np.asarray(host.lengths), terminated=np.asarray(host.terminated),
        epsilon=tabular.epsilon_schedule(agent_params, config.nepisodes), nan_episodes=np.asarray(host.nan_episodes),
        env_steps=int(np.asarray(host.env_steps, np.int64).sum()), q=q if not config.shared_table else q[None],
        compile_seconds=compile_seconds, run_seconds=loop.seconds, eval_returns=eval_returns,
        eval_lengths=eval_lengths, eval_success=eval_success, selected=selected, complete=not stopped,
        chunks_done=loop.chunks_done, start_chunk=start_chunk, eval_seconds=eval_seconds,
        episodes_done=np.minimum(np.asarray(host.episode), config.nepisodes),
        episodes_finished=int(np.asarray(host.episode, np.int64).sum()), budget=trainer.budget,
        learning_target=getattr(env, "learning_target", None), plan=repr(trainer.plan), restored_env_steps=restored,
        final_table_choice=final_choice,
        target_checks=checks if check_every else None, target_every=check_every,
        target_met_chunk=loop.checked_done_at, target_check_seconds=loop.check_seconds,
        checkpoint_seconds=loop.save_seconds, copy_seconds=copy_seconds, record_parts=parts)


# ---- a population of runs ----------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class Population:
    """Rows of one trainer's runs trained as one program (a sweep's group): ``Trainer.init`` / ``run_chunk``
    vmapped over a leading row axis, the rows split over ``mesh``'s devices (None: one device), each row with
    its own key, agent and env parameters. :func:`jaxrobo.training.train.train` runs it when given one
    (:func:`run_population`).

    ``key_data``: the rows' ``jax.random.key_data`` (``[n_rows, ...]``, host). ``finish(carry, key_data,
    env_params)``: traceable, the rows' measures at the end (a dict of ``[rows]`` arrays), compiled with the
    chunk; ``finish_parts``: what ``finish`` is built from besides the trainer (the rows' count is added), which
    names its kept traces (:func:`jaxrobo.speed.reuse.compile_reusing`). ``max_seconds``: the rows stop training
    before a chunk once this much time has passed (at least one chunk run), not stopped, not complete."""

    key_data: np.ndarray
    finish: Callable[[Runner, jax.Array, Any], dict[str, jax.Array]]
    mesh: Any = None
    finish_parts: tuple = ()
    max_seconds: float | None = None

    @property
    def n_rows(self) -> int:
        return int(np.shape(self.key_data)[0])

    @property
    def n_padded(self) -> int:
        """Rows with the padding that splits them evenly over the mesh (padding rows repeat the last row and are
        dropped from every answer)."""
        from jaxrobo.speed import sharding

        return sharding.padded_size(self.n_rows, self.mesh)

    def padded(self, agent_params: Any, env_params: Any) -> tuple[Any, Any, Any]:
        """``(key_data, agent_params, env_params)`` padded to :attr:`n_padded` rows, host arrays."""
        from jaxrobo.speed import sharding

        return sharding.pad_rows((self.key_data, agent_params, env_params), self.n_padded)

    def template(self, trainer: Trainer, agent_params: Any, env_params: Any) -> Any:
        """The rows' carry as shapes (``jax.ShapeDtypeStruct`` leaves, padded rows), traced, not compiled: what a
        saved carry is checked against before it is handed to :func:`run_population` as ``initial``."""
        with trainer.plan.tracing():
            return jax.eval_shape(_population_init(trainer), *self.padded(agent_params, env_params))


@dataclasses.dataclass
class PopulationResult:
    """What :func:`run_population` ends with. ``metrics``: ``finish``'s measures per row, host arrays of
    ``n_rows`` (None when stopped). ``complete``: every row reached its budget (not cut by ``max_seconds``);
    ``stopped``: a stop ended it at a chunk boundary (its carry handed to ``checkpoint``). ``slot_steps``: the
    env slots the chunks this process ran stepped; ``restored_env_steps``: the rows' env steps in ``initial``."""

    metrics: dict[str, np.ndarray] | None
    complete: bool
    stopped: bool
    chunks_done: int
    n_chunks: int
    start_chunk: int
    compile_seconds: float
    run_seconds: float
    eval_seconds: float
    slot_steps: int
    restored_env_steps: int


def _population_init(trainer: Trainer) -> Callable:
    def init(key_data, agent_params, env_params):
        return jax.vmap(trainer.init)(jax.random.wrap_key_data(key_data), agent_params, env_params)
    return init


def _population_chunk(trainer: Trainer) -> Callable:
    def chunk(runner, agent_params, env_params):
        return jax.vmap(trainer.run_chunk)(runner, agent_params, env_params)
    return chunk


def compiled_population(trainer: Trainer, population: Population, key_data: jax.Array, agent_params: Any,
                        env_params: Any, initial: Runner | None = None) -> tuple[Runner, Callable, Callable]:
    """``(carry, chunk, finish)``: the rows' carry (a fresh vmapped ``init``, run, or ``initial`` placed as that
    one would be), and the vmapped ``run_chunk`` (carry donated) and ``finish`` compiled for it under the plan.
    ``key_data`` and the parameters are padded and placed (:func:`run_population`). On one device with the plan's
    ``reuse_traces`` the three go through :func:`jaxrobo.speed.reuse.compile_reusing` (``sweep_init``,
    ``sweep_chunk``, ``sweep_finish``); over a mesh each device runs its rows
    (:func:`jaxrobo.speed.sharding.jit_batched`)."""
    from jaxrobo.speed import sharding

    plan, mesh, n = trainer.plan, population.mesh, population.n_padded
    kd, ap, ep = key_data, agent_params, env_params
    init, step, finish = _population_init(trainer), _population_chunk(trainer), population.finish
    if initial is not None:  # placed as the fresh carry is: split over the mesh's rows, else on the default device
        runner = jax.device_put(initial, sharding.shardings_like(initial, mesh, n) if mesh is not None
                                else jax.devices()[0])
    if mesh is None and plan.reuse_traces:  # on one device: traces kept by an earlier process, read back
        parts = (trainer, n, *population.finish_parts)
        if initial is None:
            runner = reuse.compile_reusing(plan, "sweep_init", init, (kd, ap, ep), parts)(kd, ap, ep)
        chunk = reuse.compile_reusing(plan, "sweep_chunk", step, (runner, ap, ep), parts, donate=(0,))
        return runner, chunk, reuse.compile_reusing(plan, "sweep_finish", finish, (runner, kd, ep), parts)
    opts = plan.xla_options
    if initial is None:
        init = sharding.jit_batched(init, mesh, n, (kd, ap, ep), compiler_options=opts)
        runner = compile_under(plan, init, kd, ap, ep)(kd, ap, ep)
    chunk = sharding.jit_batched(step, mesh, n, (runner, ap, ep), donate=(0,), compiler_options=opts)
    chunk = compile_under(plan, chunk, runner, ap, ep)
    finish = sharding.jit_batched(finish, mesh, n, (runner, kd, ep), compiler_options=opts)
    return runner, chunk, compile_under(plan, finish, runner, kd, ep)


def run_population(trainer: Trainer, population: Population, agent_params: Any, env_params: Any,
                   progress: ProgressFn | None = None, *, initial: Runner | None = None, start_chunk: int = 0,
                   checkpoint: CheckpointFn | None = None, checkpoint_every: int = 0,
                   checkpoint_seconds: float | None = None,
                   should_stop: Callable[[], bool] | None = None) -> PopulationResult:
    """Train every row of ``population`` (``agent_params`` / ``env_params``: the rows' parameters stacked on a
    leading axis, host arrays) from a fresh carry or ``initial`` (the rows' carry after ``start_chunk`` chunks,
    padded rows included, e.g. loaded against :meth:`Population.template`) until every row's budget or
    ``max_seconds``, then ``finish``: the population body of :func:`jaxrobo.training.train.train`. The loop and
    its hooks are :func:`run_chunks`'s, as a single run's; the carry goes to ``checkpoint`` at its cadence and
    when stopped, not after the last chunk (the measures are what a finished population keeps)."""
    from jaxrobo.speed import sharding

    if agent_params is None or env_params is None:
        raise ValueError("train(population=...): agent_params and env_params must be the rows' parameters, stacked")
    if trainer.plan.devices != 1:
        raise ValueError("train(population=...): the rows are split over population.mesh, not each row's envs "
                         f"(the plan has devices={trainer.plan.devices}; give a plan of one device)")
    kd, ap, ep = sharding.put_batch(population.padded(agent_params, env_params), population.mesh)
    # Read before the first chunk takes the carry's buffers: the padding rows' steps are not the rows'.
    restored = 0 if initial is None else int(np.asarray(host_get(initial.env_steps), np.int64)[:population.n_rows]
                                              .sum())
    t0 = time.perf_counter()
    runner, chunk, finish = compiled_population(trainer, population, kd, ap, ep, initial)
    stats = compiled_progress(runner, trainer)
    jax.block_until_ready(runner)
    compile_seconds = time.perf_counter() - t0
    total, unit = trainer.budget_total
    c, n_chunks = trainer.config, trainer.max_chunks()
    slots = float(c.chunk_steps) * c.n_envs * population.n_rows
    loop = run_chunks(lambda r: chunk(r, ap, ep), runner, n_chunks, start_chunk=start_chunk, read=stats,
                      total=total, progress=progress, should_stop=should_stop, max_seconds=population.max_seconds,
                      unit=unit, slots_per_chunk=slots, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                      checkpoint_seconds=checkpoint_seconds, save_at_end=False)
    metrics, eval_seconds = None, 0.0
    if not loop.stopped:
        t_eval = time.perf_counter()  # the rows' measures (a greedy evaluation among them), gathered to the host
        out = sharding.gather(finish(loop.carry, kd, ep))
        metrics = {k: np.asarray(v)[:population.n_rows] for k, v in out.items()}
        eval_seconds = time.perf_counter() - t_eval
    return PopulationResult(metrics, complete=not loop.stopped and loop.done >= total, stopped=loop.stopped,
                            chunks_done=loop.chunks_done, n_chunks=n_chunks, start_chunk=start_chunk,
                            compile_seconds=compile_seconds, run_seconds=loop.seconds, eval_seconds=eval_seconds,
                            slot_steps=loop.chunks_done * c.chunk_steps * c.n_envs * population.n_rows,
                            restored_env_steps=restored)


@contextlib.contextmanager
def _saved_after_evaluation(checkpoint: CheckpointFn | None, evaluates: bool) -> Iterator[None]:
    """Inside the block, a checkpoint that saves in a thread (one with ``hold`` and ``release``:
    :class:`jaxrobo.training.checkpoint.SaveInThread`) starts its closing save's copy of the carry only when the
    block ends (the greedy evaluation read back), however it ends."""
    hold = getattr(checkpoint, "hold", None) if evaluates else None
    if hold is None:
        yield
        return
    hold()
    try:
        yield
    finally:
        checkpoint.release()


@contextlib.contextmanager
def _joined(threads: list[threading.Thread]) -> Iterator[None]:
    """Wait for ``threads`` (those in the list when the block ends) on the way out, however the block ends: a run
    that stops (or fails) while the evaluation still compiles would otherwise end its process with a thread inside
    XLA's compiler, which the C++ runtime aborts when the thread comes back."""
    try:
        yield
    finally:
        for thread in threads:
            thread.join()


def _in_thread(out: list, fn: Callable, *args: Any) -> threading.Thread:
    """A started thread appending ``fn(*args)`` to ``out``; an exception leaves ``out`` as it was (the caller runs
    ``fn`` again where it can raise)."""

    def work() -> None:
        try:
            out.append(fn(*args))
        except Exception:  # noqa: BLE001 - see the docstring
            pass

    thread = threading.Thread(target=work, name=f"jaxrobo-compile-{getattr(fn, '__name__', 'program')}", daemon=True)
    thread.start()
    return thread


def prepare_evaluation(trainer: Trainer, flights: Flights, runner: Runner, key: jax.Array
                       ) -> list[threading.Thread]:
    """Compile the greedy flights of :func:`evaluate_tables` (and so of the learning-target checks) in a thread,
    and what picks their tables and keys (:class:`Flights`' small programs) in another, from the carry's shapes,
    while the caller goes on training: the device trains while the host compiles, and the evaluation at the end
    flies at once. A failure here is left to the flight itself, which compiles again and raises where the caller
    sees it."""
    config = trainer.config
    n_eval = evaluated_tables(config)
    agents = jax.eval_shape(lambda r: r.agent if config.shared_table
                            else jax.tree.map(lambda x: x[:n_eval], r.agent), runner)
    keys, fresh = jax.eval_shape(lambda k: evaluation_keys(k, n_eval), key)
    episodes = max(config.eval_episodes, 1)

    carry = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, weak_type=getattr(x, "weak_type", False)),
                         runner)
    run_key = jax.ShapeDtypeStruct(key.shape, key.dtype)

    def evaluation() -> None:
        flights.prepare(keys, agents, episodes, over_tables=True, shared=config.shared_table)
        if n_eval > 1:
            one = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), agents)
            flights.prepare(fresh, one, episodes, over_tables=False)

    def inputs() -> None:  # small, but a GPU compiles a sort for 0.5-0.8 s (H200): beside the flights
        if trainer.target_every():
            flights.check_inputs.prepare(carry, run_key, np.int32(0))
        flights.eval_inputs.prepare(carry, run_key)
        if n_eval > 1:
            flights.one_table.prepare(agents, np.int32(0))

    return [_in_thread([], evaluation), _in_thread([], inputs)]


def pick_tables(trainer: Trainer, runner: Runner) -> tuple[jax.Array | None, Any]:
    """The tables a greedy evaluation (and a learning-target check) flies: ``(index, tables)``. A shared table:
    ``(None, the table)``. Per-env tables: the :func:`evaluated_tables` envs whose latest recorded episode was best
    by the task's ranking (:func:`jaxrobo.task.env.ranking`), in env order (``index``), and their tables stacked;
    with ``n_envs <= eval_envs``, every env's, in order. Traceable."""
    config = trainer.config
    if config.shared_table:
        return None, runner.agent
    rank = ranking(getattr(trainer.env, "learning_target", None))
    last_slot = jnp.clip(runner.episode - 1, 0, runner.returns.shape[1] - 1)[:, None]
    recent = jnp.take_along_axis(runner.returns if rank.episode_figure == "return" else runner.lengths,
                                 last_slot, axis=1)[:, 0].astype(jnp.float32)
    index = jnp.sort(jnp.argsort(-recent if rank.higher else recent, stable=True)[:evaluated_tables(config)])
    return index, jax.tree.map(lambda x: x[index], runner.agent)


def target_check(trainer: Trainer, flights: Flights, key: jax.Array, log: list) -> Callable[[Runner, int], bool]:
    """The learning-target stop's ``check(carry, chunks_done)`` for :func:`run_chunks`: whether the carry's policy
    has learned, judged as the final evaluation judges it (:func:`evaluate_tables`, the same flights and programs,
    so the check compiles nothing the evaluation would not).

    The shared table, or the ``eval_envs`` per-env tables whose latest episode was best (by the task's ranking),
    fly ``eval_episodes`` greedy episodes; the best of them (:func:`choose_table`) must reach the target, then reach
    it again on as many fresh episodes, so that the maximum of noisy estimates does not flatter it. The keys fold
    the chunk count into ``fold_in(key, 4)`` of the run's key (the evaluation's are 1 and 2, the final table
    choice's 3): never those of training or of the final evaluation. Each check appends ``{"chunks", "score",
    "confirmed"}`` to ``log`` (``confirmed`` NaN when the first flight missed)."""
    config, target = trainer.config, trainer.env.learning_target

    def figure(out: dict[str, Any]) -> np.ndarray:
        return table_figures(out, target)[target.metric].astype(np.float64).mean(axis=-1)

    def check(carry: Runner, chunks_done: int) -> bool:
        keys, confirm, tables = flights.check_inputs(carry, key, np.int32(chunks_done))
        out = flights.fly(keys, tables, config.eval_episodes, over_tables=True, shared=config.shared_table)
        best, _ = choose_table(table_figures(out, target), target)
        score = float(figure(out)[best])
        confirmed = float("nan")
        if bool(target.reached(score)):
            if config.shared_table:  # the one table again, on other keys: the same program
                again = flights.fly(confirm, tables, config.eval_episodes, over_tables=True, shared=True)
            else:
                table = flights.one_table(tables, np.int32(best))
                again = flights.fly(confirm, table, config.eval_episodes, over_tables=False)
            confirmed = float(figure(again).reshape(-1)[0])
        log.append({"chunks": chunks_done, "score": score, "confirmed": confirmed})
        return bool(target.reached(confirmed))

    return check


@dataclasses.dataclass(frozen=True)
class EvalProgress:
    """Where a greedy evaluation stands after a segment of its steps (:func:`evaluate_tables`): ``what`` it flies
    (``"tables"``: every evaluated table; ``"best table"``: the selected one on fresh episodes), ``step`` of
    ``horizon`` steps done, ``running`` of ``episodes`` still running, ``seconds`` of flying so far (after
    ``compile_seconds`` of compiling, which the ETA leaves out). The flight ends once no episode runs, so
    :attr:`eta` is an upper bound."""

    what: str
    step: int
    horizon: int
    running: int
    episodes: int
    seconds: float
    compile_seconds: float = 0.0

    @property
    def eta(self) -> float:
        """Seconds left if every remaining step takes as long as the ones so far (0 once no episode runs)."""
        if self.running == 0 or self.step >= self.horizon:
            return 0.0
        return self.seconds / max(self.step, 1) * (self.horizon - self.step)


#: Segments a greedy evaluation's horizon is cut into (:func:`fly`): a progress report after each, and the
#: flight ends at the first boundary after its last episode ended.
EVAL_SEGMENTS = 10


class PerShape:
    """``jax.jit(fn)`` compiled once per structure, shapes and dtypes of its arguments and kept; :meth:`prepare`
    compiles it ahead from abstract values (``jax.ShapeDtypeStruct``: a thread may do it while the device trains).
    Over several devices (``devices > 1``) the arguments' shardings vary between calls: jit compiles as they
    come."""

    def __init__(self, fn: Callable, devices: int = 1) -> None:
        self._jitted, self._devices = jax.jit(fn), devices
        self._kept: dict[str, Callable] = {}
        self._lock = threading.Lock()

    def _compiled(self, args: tuple) -> Callable:
        # Lowered from abstract values whether given arrays or not: the same program (and persistent-cache key)
        # whichever comes first, a call or a thread's prepare.
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype,
                                                               weak_type=bool(getattr(x, "weak_type", False))), args)
        name = str((jax.tree.structure(abstract), jax.tree.leaves(abstract)))
        with self._lock:
            if name not in self._kept:
                self._kept[name] = self._jitted.lower(*abstract).compile()
            return self._kept[name]

    def prepare(self, *args: Any) -> None:
        if self._devices == 1:
            self._compiled(args)

    def __call__(self, *args: Any) -> Any:
        return self._jitted(*args) if self._devices > 1 else self._compiled(args)(*args)


class Flights:
    """Greedy flights of a trainer's tables (:meth:`~jaxrobo.training.trainer.Trainer.evaluate_episodes`'s outcomes,
    host arrays), flown in :data:`EVAL_SEGMENTS` segments of the horizon (:func:`jaxrobo.task.rollout.rollout_advance`:
    the same keys and steps, so the same numbers), each program compiled once per shape and kept: the learning-target
    checks during training and the final evaluation fly the same programs, so the evaluation compiles nothing
    new. :meth:`prepare` compiles them ahead (a thread may do it while the device trains).

    A run whose envs are split over several devices of this process flies on the first of them with the
    one-device programs: a flight is a few tables' episodes, and split it waited on the devices' exchanges (65,536
    envs over two H200s: 5.7 s warm, 54-60 s cold, against 0.06 s on one); so its figures are a one-device run's,
    and its programs compile ahead as one device's do. Over several processes the flights stay split."""

    def __init__(self, trainer: Trainer, env_params: Any) -> None:
        from jaxrobo.task import rollout

        self.trainer, self.env_params = trainer, env_params
        #: The device the flights fly on where the run's envs are split over several of this process's devices.
        self.device = env_mesh(trainer).devices.flat[0] \
            if trainer.plan.devices > 1 and jax.process_count() == 1 else None
        env, horizon = trainer.env, trainer.eval_horizon()
        self.horizon, self.steps = horizon, -(-horizon // EVAL_SEGMENTS)
        self._compiled: dict[Any, tuple[Callable, Callable, float]] = {}
        self._lock = threading.Lock()

        def start(k, n):
            return rollout.rollout_start(env, k, n, env_params)

        def advance(carry, agent, t0):
            return rollout.rollout_advance(env, trainer.eval_policy(agent), carry, t0, self.steps, horizon,
                                           env_params)
        self._start, self._advance = start, advance

        # What a flight flies and with which keys, each one small program (their parts run one by one would each
        # be a program a GPU compiles on first use), compiled ahead by prepare_evaluation where it runs.
        config, n_eval = trainer.config, evaluated_tables(trainer.config)

        def check_inputs(runner, key, chunks_done):  # target_check's keys: fold_in(key, 4), then the chunk count
            k_tables, k_confirm = jax.random.split(jax.random.fold_in(jax.random.fold_in(key, 4), chunks_done))
            _, tables = pick_tables(trainer, runner)
            confirm = jax.random.split(k_confirm, n_eval) if config.shared_table else k_confirm
            return jax.random.split(k_tables, n_eval), confirm, tables

        def eval_inputs(runner, key):
            return pick_tables(trainer, runner), evaluation_keys(key, n_eval)

        devices = trainer.plan.devices
        #: ``(runner, key, np.int32(chunks_done)) -> (keys, confirming keys, tables)`` of a learning-target check.
        self.check_inputs = PerShape(check_inputs, devices)
        #: ``(runner, key) -> ((index, tables), (keys, fresh))`` of the final evaluation (:func:`evaluate_tables`).
        self.eval_inputs = PerShape(eval_inputs, devices)
        #: ``(tables, np.int32(i)) -> table i``: the best table, flown again on fresh episodes.
        self.one_table = PerShape(lambda tables, i: jax.tree.map(lambda x: x[i], tables), devices)

    def _programs(self, keys: Any, agents: Any, n_episodes: int, over_tables: bool, shared: bool):
        shapes = jax.tree.map(lambda x: (x.shape, str(x.dtype)), (keys, agents))
        name = (over_tables, shared, n_episodes, str(shapes))
        with self._lock:  # one compile per shape, also when a thread prepares it
            if name not in self._compiled:
                t = time.perf_counter()
                start = lambda k: self._start(k, n_episodes)  # noqa: E731
                advance = self._advance
                if over_tables:
                    start = jax.vmap(start)
                    advance = jax.vmap(advance, in_axes=(0, None if shared else 0, None))
                plan = self.trainer.plan
                # Both traced, then compiled side by side (the start in a thread: XLA holds no Python lock).
                if plan.devices == 1 and plan.reuse_traces:  # traces kept by an earlier process, read back
                    parts = (self.trainer, self.env_params, self.horizon, self.steps, name)
                    start = CompilingInThread(reuse.lower_reusing(plan, "eval_start", start, (keys,), parts))
                    with _joined([start.thread]):  # never left inside XLA, whatever the advance's fate
                        carry = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype), start.lowered.out_info)
                        advance = reuse.lower_reusing(plan, "eval_advance", advance, (carry, agents, np.int32(0)),
                                                      parts).compile()
                    self._compiled[name] = (start.wait(), advance, time.perf_counter() - t)
                    return self._compiled[name]
                # Over several processes' devices, compiled as the chunk is (spmd_options), so that each flight
                # rounds as one device's does.
                one = plan.devices == 1 or self.device is not None
                opts = None if one else sharding.spmd_options(None, env_mesh(self.trainer))
                start = jax.jit(plan.traced(start), compiler_options=opts)
                advance = jax.jit(plan.traced(advance), compiler_options=opts)
                if one:  # compiled ahead (a thread may do it); over several processes' devices the
                    # inputs' shardings vary between flights: jit compiles for each as they come
                    carry = jax.eval_shape(start, keys)
                    start = CompilingInThread(start.lower(keys))
                    with _joined([start.thread]):
                        advance = advance.lower(carry, agents, np.int32(0)).compile()
                    start = start.wait()
                self._compiled[name] = (start, advance, time.perf_counter() - t)
            return self._compiled[name]

    def prepare(self, keys: Any, agents: Any, n_episodes: int, *, over_tables: bool, shared: bool = False) -> None:
        """Compile the flight of these shapes (abstract values do: ``jax.ShapeDtypeStruct``) without flying."""
        self._programs(keys, agents, n_episodes, over_tables, shared)

    def fly(self, keys: jax.Array, agents: Any, n_episodes: int, *, over_tables: bool, shared: bool = False,
            progress: Callable[[EvalProgress], None] | None = None, what: str = "tables") -> dict[str, np.ndarray]:
        """``n_episodes`` greedy episodes per key. ``over_tables``: ``keys`` and ``agents`` have a leading table
        axis (``shared``: one agent for every key, as a shared table is evaluated). The flight ends at the first
        segment boundary after its last episode ended; ``progress`` hears an :class:`EvalProgress` after each."""
        from jaxrobo.task import rollout

        if self.device is not None:  # the picked tables and keys, split as the run's carry, to the one device
            # through the host: no copy between the devices while the run's programs may still hold them
            typed = jax.dtypes.issubdtype(keys.dtype, jax.dtypes.prng_key)
            data, agents = jax.device_put(jax.device_get((jax.random.key_data(keys) if typed else keys, agents)),
                                          self.device)
            keys = jax.random.wrap_key_data(data, impl=jax.random.key_impl(keys)) if typed else data
        start, advance, compile_seconds = self._programs(keys, agents, n_episodes, over_tables, shared)
        carry = start(keys)
        running = count = int(np.prod(carry["alive"].shape))
        t0 = time.perf_counter()
        step = 0
        while step < self.horizon and running:
            carry = advance(carry, agents, np.int32(step))
            step = min(step + self.steps, self.horizon)
            running = int(np.asarray(carry["alive"]).sum())  # the host waits for the segment here
            if progress is not None:
                progress(EvalProgress(what, step, self.horizon, running, count, time.perf_counter() - t0,
                                      compile_seconds))
        return jax.device_get(rollout.outcomes(rollout.rollout_end(carry)))


def fly(trainer: Trainer, keys: jax.Array, agents: Any, n_episodes: int, env_params: Any, *, over_tables: bool,
        shared: bool = False, progress: Callable[[EvalProgress], None] | None = None,
        what: str = "tables") -> dict[str, np.ndarray]:
    """One :meth:`Flights.fly` of ``trainer``'s tables (its programs compiled for this flight alone)."""
    return Flights(trainer, env_params).fly(keys, agents, n_episodes, over_tables=over_tables, shared=shared,
                                            progress=progress, what=what)


class _EvaluationStopped(Exception):
    """A stop asked for between two segments of the greedy evaluation (:func:`run_training`)."""


def evaluated_tables(config: Any) -> int:
    """How many of a run's trained tables its greedy evaluation flies: the shared one, or ``eval_envs`` of them
    (:func:`pick_tables` says which)."""
    return 1 if config.shared_table else min(config.eval_envs, config.n_envs)


def evaluation_keys(key: jax.Array, n_tables: int) -> tuple[jax.Array, jax.Array]:
    """The greedy evaluation's keys from the run's ``key``: one per evaluated table (``[n_tables]``), and the key
    of the best table's second flight, on fresh episodes."""
    return jax.random.split(jax.random.fold_in(key, 1), n_tables), jax.random.fold_in(key, 2)


def table_figures(out: dict[str, Any], target: Any) -> dict[str, np.ndarray]:
    """A greedy flight's outcomes (``return``, ``length``, maybe ``arrived``; ``[tables, episodes]`` each) as
    per-table records keyed by :data:`jaxrobo.task.env.TARGET_METRICS`: ``mean_return``, ``mean_length`` and, for a
    task whose learning target is a ``success_rate`` and whose flight records arrivals, ``success_rate``."""
    per_table = {"mean_return": np.asarray(out["return"]), "mean_length": np.asarray(out["length"])}
    if target is not None and target.metric == "success_rate" and "arrived" in out:
        per_table["success_rate"] = np.asarray(out["arrived"])
    return per_table


def choose_table(per_table: dict[str, Any], target: Any) -> tuple[int, float | None]:
    """The best of a run's evaluated tables and, where this flight decides it, the figure the run is judged by.

    ``per_table``: :func:`table_figures` of the evaluated tables. The best table follows the task's learning
    target (:meth:`jaxrobo.task.env.Ranking.best_table` of :func:`~jaxrobo.task.env.ranking`). The figure is the
    target's metric of that table on these episodes (the mean over them), or None where the run is judged by the
    best table flown again on fresh episodes (:func:`evaluate_tables`' ``selected``: several tables and a
    ``mean_length`` / ``mean_return`` target, since the best of several noisy estimates flatters the table; a
    ``success_rate`` stays this flight's, the only one that records arrivals) or where this flight does not record
    the target's metric (no target; no arrivals)."""
    best = ranking(target).best_table(per_table)
    metric = None if target is None else target.metric
    several = len(per_table["mean_return"]) > 1
    if metric not in per_table or (several and metric in ("mean_length", "mean_return")):
        return best, None
    return best, float(np.asarray(per_table[metric], np.float64).mean(axis=1)[best])


def evaluate_tables(trainer: Trainer, runner: Runner, key: jax.Array, env_params: Any,
                    progress: Callable[[EvalProgress], None] | None = None, flights: Flights | None = None
                    ) -> tuple[np.ndarray, np.ndarray, dict[str, Any] | None, np.ndarray | None]:
    """Greedy evaluation of ``eval_envs`` trained tables (:func:`pick_tables`: those whose latest episode was best;
    the shared one: once), ``eval_episodes`` each: ``(returns, lengths, selected, success)``, the first two
    ``[tables, eval_episodes]``. With several tables
    the best one is evaluated again on fresh episodes (``selected``: its env's index, returns and lengths), so its
    figure is not the maximum of noisy estimates; "best" follows the task's learning target
    (:func:`jaxrobo.task.env.ranking`: by success rate, return or length, in its direction). ``key`` is the run's
    key.

    Both flights go in segments (:func:`fly`): ``progress`` hears an :class:`EvalProgress` after each.

    ``success``: for a task whose learning target is a ``success_rate`` and whose task variables carry an
    ``arrived`` flag (QuadcopterGoto, ArmReach), whether each of those episodes arrived, ``[tables,
    eval_episodes]``, read from the same flight as the returns; None for any other task.

    ``flights``: the run's :class:`Flights` (its compiled programs reused), else one of its own."""
    config = trainer.config
    flights = Flights(trainer, env_params) if flights is None else flights
    n_eval = evaluated_tables(config)
    (index, tables), (keys, fresh) = flights.eval_inputs(runner, key)
    out = flights.fly(keys, tables, config.eval_episodes, over_tables=True, shared=config.shared_table,
                      progress=progress)
    target = getattr(trainer.env, "learning_target", None)
    per_table = table_figures(out, target)
    eval_returns, eval_lengths = per_table["mean_return"], per_table["mean_length"]
    success = per_table.get("success_rate")
    selected = None
    if n_eval > 1:
        best, _ = choose_table(per_table, target)  # the summary's best table: the task's target decides
        table = flights.one_table(tables, np.int32(best))
        sel = flights.fly(fresh, table, config.eval_episodes, over_tables=False, progress=progress,
                          what="best table")
        selected = {"table": int(np.asarray(index)[best]), "returns": np.asarray(sel["return"]),
                    "lengths": np.asarray(sel["length"])}
    return eval_returns, eval_lengths, selected, success


# ---- stopping on a signal ----------------------------------------------------------------------------------------
class StopOnSignal:
    """SIGINT / SIGTERM ask a run to stop at its next chunk boundary, for the command lines.

    ``with StopOnSignal() as stop: train(..., should_stop=stop)``: ``stop()`` says whether a signal came,
    ``stop.signum`` / ``stop.name`` which one. ``notice(signum)`` runs on the first one (to say what happens
    next). A second signal quits without waiting for the chunk: with ``second="default"`` it acts as it would
    without this handler (KeyboardInterrupt for SIGINT, termination for SIGTERM), with ``second="exit"`` it
    raises ``SystemExit(128 + signum)``. The previous handlers come back on exit. Handlers are installed only
    in the main thread (Python allows no others); elsewhere ``stop()`` stays False.

    ``abandon(signum) -> bool``, if given, is for a main thread that can be inside one long native call (a
    compiled training step runs no Python signal handler until it returns): :data:`PATIENCE_SECONDS` after the
    first signal (at once after a second), a watchdog thread calls it, again every tenth of a second until it
    returns True; it is to end the process itself (keeping what is already kept) where the main thread cannot
    stop soon, and return False where the main thread will see ``stop()`` by itself."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, notice: Callable[[int], None] | None = None, second: str = "default",
                 abandon: Callable[[int], bool] | None = None) -> None:
        if second not in ("default", "exit"):
            raise ValueError(f"second={second!r}: expected 'default' or 'exit'")
        self.notice, self.second, self.abandon = notice, second, abandon
        self.signum: int | None = None
        self._old: dict[int, Any] = {}
        self._pipe: tuple[int, int] | None = None
        self._wakeup_old = -1

    #: Seconds after a second signal that the process ends even if Python code cannot run its handler (the main
    #: thread inside a long XLA compile or a device wait runs no Python signal handler until it returns).
    GRACE_SECONDS = 2.0
    #: Seconds after a first signal that ``abandon`` is first called.
    PATIENCE_SECONDS = 3.0

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
            self._start_watchdog()
        return self

    def _start_watchdog(self) -> None:
        """Python runs a signal handler only between bytecodes of the main thread; the C-level handler still
        writes the signal number to the wakeup fd at once. A thread reading it counts the signals: after the
        second, if the main thread has not ended the process within :data:`GRACE_SECONDS`, the process ends
        with the signal's default action (the run's last checkpoint stays on disk)."""
        try:
            r, w = os.pipe()
            os.set_blocking(w, False)
            self._wakeup_old = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        except (OSError, ValueError):
            return
        self._pipe = (r, w)

        def abandon_after(signum: int, seconds: float) -> None:
            time.sleep(seconds)
            while self._pipe is not None and not self.abandon(signum):
                time.sleep(0.1)

        def start_abandon(signum: int, seconds: float) -> None:
            threading.Thread(target=abandon_after, args=(signum, seconds), name="StopOnSignal-abandon",
                             daemon=True).start()

        def watch() -> None:
            seen = 0
            while True:
                try:
                    data = os.read(r, 64)
                except OSError:
                    return
                if not data:
                    return
                for signum in data:
                    if signum in self.SIGNALS:
                        seen += 1
                        if self.abandon is not None:
                            start_abandon(signum, 0.0 if seen >= 2 else self.PATIENCE_SECONDS)
                        if seen >= 2:
                            time.sleep(self.GRACE_SECONDS)
                            if self._pipe is None:  # handled and left meanwhile
                                return
                            os.write(2, f"\n{signal.Signals(signum).name} twice: quitting now\n".encode())
                            _default_action(signum)

        self._watchdog = threading.Thread(target=watch, name="StopOnSignal-watchdog", daemon=True)
        self._watchdog.start()

    def _handle(self, signum: int, _frame: Any) -> None:
        if self.second == "exit" and self.signum is not None:
            raise SystemExit(128 + signum)
        first = self.signum is None
        self.signum = signum
        if self.second == "default":  # the next one of this signal meets its old handler
            signal.signal(signum, self._old.get(signum, signal.SIG_DFL))
        if first and self.notice is not None:
            self.notice(signum)

    @property
    def name(self) -> str | None:
        """``"SIGINT"`` / ``"SIGTERM"`` once one came, else None."""
        return None if self.signum is None else signal.Signals(self.signum).name

    def __call__(self) -> bool:
        return self.signum is not None

    def __exit__(self, *_exc: Any) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            signal.set_wakeup_fd(self._wakeup_old)
            for fd in reversed(pipe):  # the write end first: the watchdog's read then returns b""
                os.close(fd)


def agreed_stop(stop: StopOnSignal) -> Callable[[], bool]:
    """``stop`` as every process under ``jax.distributed`` answers it (one process: ``stop`` itself): True where a
    signal reached any of them, and a process it did not reach takes that signal as its own (``stop.signum``), so
    that each stops at the same chunk and exits with the same status. A collective: the run asks it at the same
    points in every process (before each chunk, between segments and groups); a stop asked in one process alone
    left the others running the next chunk's collectives without it (Gloo's 'collective mismatch', both aborted)."""
    if jax.process_count() == 1:
        return stop

    def asked() -> bool:
        signum = sharding.largest(stop.signum or 0)[0]
        if signum and stop.signum is None:
            stop.signum = signum
        return signum != 0

    return asked


def _default_action(signum: int) -> None:
    """End the process at once, from any thread, with the exit status a shell reports for ``signum`` (Python
    cannot restore a signal's default disposition outside the main thread)."""
    os._exit(128 + signum)
