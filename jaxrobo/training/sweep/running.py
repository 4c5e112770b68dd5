"""Running a planned sweep: every group one compiled program, its rows vmapped (and sharded) over a leading axis.

:class:`GroupRunner` makes one group a :class:`~jaxrobo.training.driver.Population` of its trainer's runs and its
measures (the rows' metrics and greedy evaluation) and trains it with :func:`jaxrobo.training.train.train`, the entry
every training goes through (``Trainer.init`` / ``Trainer.run_chunk`` vmapped over the rows, the host loop of
:func:`jaxrobo.training.driver.run_chunks`, the callbacks); :func:`run_plan` runs the groups of a
:class:`~jaxrobo.training.sweep.planning.SweepPlan` one after the other, saving each finished group through
:mod:`jaxrobo.training.sweep.state` when given a state directory, and gathers the rows into a :class:`SweepResult`.

Public surface: :data:`METRICS`, :class:`SweepResult`, :class:`GroupRunner`, :func:`run_sweep`, :func:`run_plan`,
:class:`SweepInterrupted`.
"""
from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.training import driver
from jaxrobo.training import train as training
from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.core import rng
from jaxrobo.core.struct import rules
from jaxrobo.training.sweep import state
from jaxrobo.training.sweep.planning import SweepPlan, plan_sweep
from jaxrobo.tabular.learner import AgentParams
from jaxrobo.task.env import Ranking, ranking
from jaxrobo.training.callbacks import as_callbacks
from jaxrobo.training.trainer import Runner, Trainer

#: Metrics written for every row; ``final_return`` (mean return of the last 100 episodes) ranks by default.
#: ``eval_success_rate``: the greedy episodes' success for a task whose learning target is a success rate.
#: ``best_100_window``: each env's best 100-episode moving mean of the figure the task's learning target ranks
#: by (:func:`jaxrobo.task.env.ranking`: return or length, best in its direction), averaged over envs;
#: ``best_100_mean_length`` stays the seed's mean of the 100 longest episodes.
METRICS = ("final_return", "final_length", "mean_length", "best_100_mean_length", "highest_reward",
           "episodes_done", "env_steps", "physics_nan_episodes", "eval_mean_length", "eval_mean_return",
           "eval_success_rate", "best_100_window")

#: Metrics where a lower value is better whatever the task (no direction from its learning target).
_LOWER_IS_BETTER = ("physics_nan_episodes",)
#: Metrics of episode lengths, whose direction is the target's when it ranks by length (a minimum-time task).
_LENGTH_METRICS = ("final_length", "mean_length", "eval_mean_length")


def higher_is_better(metric: str, rank: Ranking) -> bool:
    """Which way ``metric`` improves for a task ranked by ``rank``: returns and success rates up; lengths the
    way the target says when it ranks by length (else up: the seed's tasks are kept going); ``best_100_window``
    the target's way; NaN episodes down; ``best_100_mean_length`` (the longest, by definition) up."""
    if metric in _LOWER_IS_BETTER:
        return False
    if metric == "best_100_window" or (metric in _LENGTH_METRICS and rank.episode_figure == "length"):
        return rank.higher
    return True


class SweepInterrupted(Exception):
    """The sweep's stop hook fired; ``done`` of ``total`` groups are finished (and saved in ``state_dir``);
    ``partial``: ``(group, chunks_done, n_chunks)`` of the group in progress when its carry was saved at that
    chunk boundary (a resume goes on from there), else None."""

    def __init__(self, done: int, total: int, state_dir: str | None,
                 partial: tuple[int, int, int] | None = None):
        super().__init__(f"interrupted with {done} of {total} groups finished")
        self.done, self.total, self.state_dir, self.partial = done, total, state_dir, partial

    @property
    def where(self) -> str:
        """``"1 of 2 groups finished"`` and, with a saved carry, ``"; group 2 saved after chunk 3 of 9"``."""
        out = f"{self.done} of {self.total} groups finished"
        if self.partial is not None:
            g, k, n = self.partial
            out += f"; group {g + 1} saved after chunk {k} of {n}"
        return out


@dataclasses.dataclass
class SweepResult:
    """One row per (configuration, seed), plus how long each compiled group took."""

    env_id: str
    swept: list[str]
    rows: list[dict[str, Any]]
    groups: list[dict[str, Any]]
    wall_seconds: float
    #: What "best" means for the task (its learning target's :class:`~jaxrobo.task.env.Ranking`).
    ranking: Ranking = Ranking("length", "mean_length", True)

    @property
    def env_steps(self) -> int:
        return int(sum(r["env_steps"] for r in self.rows))

    def best(self, metric: str = "final_return") -> dict[str, Any]:
        """The configuration with the best mean of ``metric`` over its seeds: the highest, or the lowest where
        lower is better (:func:`higher_is_better`; ``higher`` in the answer says which)."""
        by_config: dict[int, list[dict[str, Any]]] = {}
        for r in self.rows:
            by_config.setdefault(r["config"], []).append(r)
        higher = higher_is_better(metric, self.ranking)
        scored = [(float(np.mean([r[metric] for r in rs])), rs) for rs in by_config.values()]
        score, rs = (max if higher else min)(scored, key=lambda t: t[0])
        out = {k: rs[0][k] for k in self.swept}
        out.update(config=rs[0]["config"], metric=metric, mean=score,
                   std=float(np.std([r[metric] for r in rs])), seeds=len(rs), higher=higher)
        return out


def _as_array(values: list[Any]) -> np.ndarray:
    arr = np.asarray(values)
    if arr.dtype.kind == "f":
        return arr.astype(np.float32)
    if arr.dtype.kind in "iu":
        return arr.astype(np.int32)
    return arr


def _stack(trees: list[Any]) -> Any:
    return jax.tree.map(lambda *xs: _as_array(list(xs)), *trees)


def _sum_last(x: jax.Array, n_axes: int) -> jax.Array:
    """``x`` summed over its last ``n_axes`` axes in one fixed order: the terms flattened (row-major), padded with
    zeros to a power of two and added pairwise, half onto half, element by element. XLA orders the terms of its
    own reductions by the program it compiles them into (one device's, several devices'), and a row's means
    moved in their last bit with the device count; element-wise adds keep the same order in every program."""
    lead = x.shape[:x.ndim - n_axes]
    m = int(np.prod(x.shape[x.ndim - n_axes:], dtype=np.int64))
    flat = x.reshape(lead + (m,))
    size = 1 << max(m - 1, 0).bit_length()
    if size != m:
        flat = jnp.concatenate([flat, jnp.zeros(lead + (size - m,), flat.dtype)], axis=-1)
    while flat.shape[-1] > 1:
        h = flat.shape[-1] // 2
        flat = flat[..., :h] + flat[..., h:]
    return flat[..., 0]


def _mean_last(x: jax.Array, n_axes: int) -> jax.Array:
    """The mean over the last ``n_axes`` axes, summed by :func:`_sum_last`."""
    return _sum_last(x, n_axes) / np.float32(np.prod(x.shape[x.ndim - n_axes:], dtype=np.int64))


def _best_window(figure: jax.Array, count: jax.Array, rank: Ranking, window: int = 100) -> jax.Array:
    """Per row, each env's best ``window``-episode moving mean of ``figure`` (``[rows, n_envs, episodes]``) over
    its first ``count`` (``[rows, n_envs]``) recorded episodes, best in ``rank``'s direction, averaged over the
    envs with any (an env with fewer than ``window`` gives the mean of all of its own):
    :func:`jaxrobo.training.summary.best_window` on the device."""
    nep = figure.shape[-1]
    count = jnp.minimum(count, nep)[..., None]
    w = jnp.maximum(jnp.minimum(window, count), 1)
    sums = jnp.concatenate([jnp.zeros_like(figure[..., :1]), jnp.cumsum(figure, axis=-1)], axis=-1)
    end = jnp.arange(nep) + 1  # a window ending after episode ``end - 1``
    start = jnp.maximum(end - w, 0)
    means = (jnp.take_along_axis(sums, jnp.broadcast_to(end, figure.shape), -1)
             - jnp.take_along_axis(sums, start, -1)) / w
    valid = (end >= w) & (end <= count)
    best = (jnp.max(jnp.where(valid, means, -jnp.inf), axis=-1) if rank.higher
            else jnp.min(jnp.where(valid, means, jnp.inf), axis=-1))
    has = count[..., 0] > 0
    return _sum_last(jnp.where(has, best, 0.0), 1) / jnp.maximum(jnp.sum(has, axis=-1), 1)


def _row_metrics(runner: Runner, n_last: int, every_slot_recorded: bool = True,
                 rank: Ranking = Ranking("length", "mean_length", True)) -> dict[str, jax.Array]:
    """Per-row performance, reduced on the device (``runner`` leaves are ``[rows, n_envs, ...]``).
    ``every_slot_recorded``: the episode budget, where every env fills its ``nepisodes`` records; under a
    run-wide budget the envs record different numbers of episodes and each figure covers the recorded ones."""
    returns = runner.returns.astype(jnp.float32)
    lengths = runner.lengths.astype(jnp.float32)
    nep = returns.shape[-1]
    figure = returns if rank.episode_figure == "return" else lengths
    count = runner.episode if not every_slot_recorded else jnp.full(runner.episode.shape, nep)
    window = {"best_100_window": _best_window(figure, count, rank)}
    if not every_slot_recorded:
        return {**_row_metrics_recorded(runner, n_last), **window}
    k = min(n_last, nep)
    best = jnp.sort(lengths, axis=-1)[..., -min(100, nep):]
    return {
        "final_return": _mean_last(returns[..., -k:], 2),
        "final_length": _mean_last(lengths[..., -k:], 2),
        "mean_length": _mean_last(lengths, 2),
        "best_100_mean_length": _mean_last(best, 2),
        "highest_reward": returns.max(axis=(-1, -2)),
        "episodes_done": runner.episode.min(axis=-1),
        "env_steps": runner.env_steps.sum(axis=-1),
        "physics_nan_episodes": runner.nan_episodes.sum(axis=-1),
        **window,
    }


def _row_metrics_recorded(runner: Runner, n_last: int) -> dict[str, jax.Array]:
    """:func:`_row_metrics` over each env's recorded episodes only (its first ``min(episode, nepisodes)``):
    ``final_*`` over each env's last ``n_last`` recorded episodes, all envs' episodes pooled."""
    returns = runner.returns.astype(jnp.float32)
    lengths = runner.lengths.astype(jnp.float32)
    nep = returns.shape[-1]
    count = jnp.minimum(runner.episode, nep)[..., None]
    index = jnp.arange(nep)
    rec = index < count
    last = rec & (index >= count - n_last)
    pooled = lambda x, m: _sum_last(jnp.where(m, x, 0.0), 2) / jnp.maximum(jnp.sum(m, axis=(-1, -2)), 1)  # noqa: E731
    top = jnp.sort(jnp.where(rec, lengths, -1.0), axis=-1)[..., -min(100, nep):]
    return {
        "final_return": pooled(returns, last),
        "final_length": pooled(lengths, last),
        "mean_length": pooled(lengths, rec),
        "best_100_mean_length": pooled(top, top >= 0),
        "highest_reward": jnp.max(jnp.where(rec, returns, -jnp.inf), axis=(-1, -2)),
        "episodes_done": runner.episode.min(axis=-1),
        "env_steps": runner.env_steps.sum(axis=-1),
        "physics_nan_episodes": runner.nan_episodes.sum(axis=-1),
    }


def _rows(tree: Any, n: int) -> Any:
    """``tree``'s leaves with ``n`` rows on their leading axis: the first ``n``, or padded to ``n`` by repeating the
    last row (as :func:`jaxrobo.speed.sharding.pad_rows` pads a group's inputs); shapes (``ShapeDtypeStruct``
    leaves) too. A tree that has ``n`` rows already is returned as it is."""
    def one(x: Any) -> Any:
        if x.shape[0] == n:
            return x
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct((n, *x.shape[1:]), x.dtype)
        return x[np.minimum(np.arange(n), x.shape[0] - 1)]
    return jax.tree.map(one, tree)


class GroupRunner:
    """One static group of a sweep as a :class:`~jaxrobo.training.driver.Population` of its trainer's runs, trained
    by :func:`jaxrobo.training.train.train` (``init`` / ``run_chunk`` vmapped over the rows, compiled with the
    trainer's plan: its compiler options, traced under it); the group's measures are :meth:`_finish`'s."""

    def __init__(self, trainer: Trainer, n_rows: int, mesh: Any = None, eval_episodes: int = 0,
                 n_last: int = 100):
        from jaxrobo.speed import sharding

        if not trainer.config.record_episodes:
            raise ValueError("a sweep needs record_episodes=True (it ranks by the last episodes' returns)")
        self.trainer, self.mesh, self.n_rows = trainer, mesh, n_rows
        self.n_padded = sharding.padded_size(n_rows, mesh)
        self.eval_episodes, self.n_last = eval_episodes, n_last
        self.compile_seconds = self.run_seconds = self.eval_seconds = 0.0
        self.complete = False
        self.slot_steps = 0
        self.start_chunk = 0  # the chunk a restored carry went on from (0: the group ran from its start)
        self.restored_env_steps = 0  # the env steps of the rows that carry had run (another process timed them)

    def population(self, key_data: np.ndarray, max_seconds: float | None = None) -> driver.Population:
        """The group's rows (``key_data``: each row's ``jax.random.key_data``) as ``train``'s population."""
        return driver.Population(np.asarray(key_data), self._finish, self.mesh, (self.n_last, self.eval_episodes),
                                 max_seconds)

    def _finish(self, runner, key_data, env_params):
        if runner.snapshots is not None:  # each row keeps the table its `jaxrobo train` run would keep
            runner = jax.vmap(self.trainer.final_table)(runner, jax.random.wrap_key_data(key_data), env_params)[0]
        rank = ranking(getattr(self.trainer.env, "learning_target", None))
        out = _row_metrics(runner, self.n_last, self.trainer.budget == "episodes", rank)
        if self.eval_episodes > 0:
            shared = self.trainer.config.shared_table
            table = runner.agent if shared else jax.tree.map(lambda x: x[:, 0], runner.agent)
            keys = jax.vmap(lambda kd: jax.random.fold_in(jax.random.wrap_key_data(kd), 1))(key_data)
            ev = jax.vmap(self.trainer.evaluate_episodes, in_axes=(0, 0, None, 0))
            episodes = ev(keys, table, self.eval_episodes, env_params)
            out["eval_mean_return"] = _mean_last(episodes["return"], 1)
            out["eval_mean_length"] = _mean_last(episodes["length"].astype(jnp.float32), 1)
            target = getattr(self.trainer.env, "learning_target", None)
            if target is not None and target.metric == "success_rate" and "arrived" in episodes:
                out["eval_success_rate"] = _mean_last(episodes["arrived"].astype(jnp.float32), 1)
        return out

    def run(self, key_data: np.ndarray, agent_params: Any, env_params: Any,
            progress: Callable[..., None] | None = None,
            max_seconds: float | None = None, stop: Callable[[], bool] | None = None,
            restore: Callable[[Callable[[], Any]], tuple[Any, int] | None] | None = None,
            checkpoint: driver.CheckpointFn | None = None,
            checkpoint_seconds: float | None = None, callbacks: Any = None) -> dict[str, np.ndarray]:
        """Train every row to its last episode (or until ``max_seconds`` of running) through
        :func:`jaxrobo.training.train.train`; per-row metrics as host arrays of length ``n_rows``.
        ``self.complete`` says whether every row finished. ``progress`` (a function of each chunk's
        :class:`~jaxrobo.training.driver.Progress`) and ``callbacks`` are ``train``'s callbacks. ``stop`` is
        polled before every chunk; when it returns True, or a callback's ``on_chunk`` returned False, the group is
        abandoned with :class:`SweepInterrupted`, after ``checkpoint(carry, chunks_done)`` saved its carry.
        ``restore(template)`` may give a saved ``(carry, chunks_done)`` to go on from, checked against
        ``template()`` (the rows' carry as shapes); the chunks are deterministic functions of the carry, so the
        rows end the same. ``checkpoint`` is also called every ``checkpoint_seconds`` at a chunk boundary."""
        population = self.population(key_data, max_seconds)
        saved = None
        if restore is not None:
            saved = restore(lambda: population.template(self.trainer, agent_params, env_params))
        initial, start_chunk = (None, 0) if saved is None else saved
        trainer = self.trainer
        result = training.train(trainer.env, trainer.config, agent_params, env_params,
                                [c for c in (progress, as_callbacks(callbacks)) if c is not None],
                                initial=initial, start_chunk=start_chunk, checkpoint=checkpoint,
                                checkpoint_seconds=checkpoint_seconds, should_stop=stop, trainer=trainer,
                                population=population)
        self.start_chunk, self.restored_env_steps = result.start_chunk, result.restored_env_steps
        self.compile_seconds = result.compile_seconds
        if result.stopped:
            partial = None if checkpoint is None else (0, result.chunks_done, result.n_chunks)
            raise SweepInterrupted(0, 1, None, partial)
        self.complete, self.slot_steps = result.complete, result.slot_steps
        self.run_seconds, self.eval_seconds = result.run_seconds, result.eval_seconds
        return result.metrics


def run_sweep(env_id: str, points: Sequence[Mapping[str, Any]], seeds: Sequence[int] = (0,),
              preset: str = "default", agent: str | None = None, overrides: Mapping[str, Any] | None = None,
              mesh: Any = None, eval_episodes: int = 0, n_last: int = 100,
              log: Callable[[str], None] | None = None,
              progress: Callable[[int, int], None] | None = None,
              compiler_options: dict[str, Any] | None = None, max_seconds: float | None = None,
              state_dir: str | None = None, should_stop: Callable[[], bool] | None = None,
              callbacks: Any = None) -> SweepResult:
    """Train every point × seed; rows grouped by static settings, one compiled program per group.

    ``points`` map swept keys to values (see :func:`classify`); ``overrides`` apply to every point (like
    ``--set``); ``max_seconds`` stops each group's training early (its rows then have ``episodes_done`` below
    ``nepisodes`` and the group ``complete: False``). Raises :class:`ConfigError` naming the key for any bad
    key or value, before compiling. ``state_dir`` and ``should_stop`` make it resumable, ``callbacks`` hear every
    group's training: see :func:`run_plan`.
    """
    plan = plan_sweep(env_id, points, seeds, preset, agent, overrides, eval_episodes, n_last, compiler_options,
                      max_seconds)
    return run_plan(plan, mesh, log, progress, state_dir, should_stop, callbacks=callbacks)


#: Default cadence of a sweep's group carry: at the first chunk boundary this long after the last save (as
#: ``jaxrobo train`` saves its carry), besides the save when the sweep is stopped.
GROUP_CHECKPOINT_SECONDS = 300.0


def run_plan(plan: SweepPlan, mesh: Any = None, log: Callable[[str], None] | None = None,
             progress: Callable[[int, int], None] | None = None, state_dir: str | None = None,
             should_stop: Callable[[], bool] | None = None, state_extra: Mapping[str, Any] | None = None,
             checkpoint_seconds: float | None = GROUP_CHECKPOINT_SECONDS, callbacks: Any = None) -> SweepResult:
    """Run a planned sweep, group by group: each group one :func:`jaxrobo.training.train.train` of its rows
    (:class:`GroupRunner`'s population), whose callbacks are ``progress`` (a function of each chunk's
    :class:`~jaxrobo.training.driver.Progress`) and ``callbacks`` (told of every group's start, chunks and end;
    an ``on_chunk`` that returns False stops the sweep as ``should_stop`` does).

    ``state_dir`` makes the sweep resumable: the sweep's settings, the code's versions and their fingerprint go
    to ``state_dir/sweep_state.json`` before the first compile (with ``state_extra``, kept but not compared), the
    row metrics of every finished group to ``state_dir/checkpoint.npz`` (rewritten atomically after each group;
    an empty one at the start), and the carry of the group in progress to ``state_dir/group_<g>.npz`` every
    ``checkpoint_seconds`` at a chunk boundary and when the sweep is stopped (removed once the group is
    finished). Running the same plan again on the same ``state_dir`` skips the saved groups, goes on inside a
    saved group from its last chunk, and gives the same rows; a state saved by other settings or other code
    raises :class:`ConfigError` before anything compiles. ``should_stop`` is polled before each group and before
    each training chunk; when it returns True the sweep saves the carry of the group it is in and raises
    :class:`SweepInterrupted`. With several processes only process 0 writes and the group carries are not
    saved (a resumed group starts from its first chunk); the others read ``state_dir`` if they are given it (a
    shared file system).
    """
    log = log or (lambda _msg: None)
    planned = plan.groups
    saved: dict[int, dict[str, Any]] = {}
    fingerprint = None
    # A group's carry is saved and read by one process only (a sharded carry over several hosts is not).
    carries = state_dir is not None and jax.process_count() == 1
    if state_dir is not None:
        opened = state.open_state(state_dir, plan, state_extra)
        fingerprint = opened["fingerprint"]
        saved = state.load_checkpoint(state_dir, plan, fingerprint)
        in_progress = [g for g in range(len(planned))
                       if g not in saved and os.path.exists(state.group_carry_path(state_dir, g))]
        if carries:
            for g in in_progress:  # a damaged or foreign carry is refused now, not once its group has compiled
                state.check_group_carry(state_dir, fingerprint, g)
        if saved or in_progress:
            log(f"resuming: {len(saved)} of {len(planned)} groups already finished in {state_dir}"
                + (f"; group {in_progress[0] + 1} goes on from its last saved chunk" if in_progress else "")
                + ("" if carries else "; with several processes an unfinished group starts from its first chunk"))
        elif jax.process_index() == 0:
            state.save_checkpoint(state_dir, fingerprint, plan, saved)

    rows: list[dict[str, Any]] = []
    timings: list[dict[str, Any]] = []
    t_all = time.perf_counter()
    for p in planned:
        g, static, spec, meta = p.index, p.static, p.spec, p.meta
        label = ", ".join(f"{k}={v}" for k, v in static) or "all"
        if g in saved:
            log(f"group {g + 1}/{len(planned)} [{label}]: finished before, read from {state_dir}")
        else:
            if should_stop is not None and should_stop():
                raise SweepInterrupted(len(saved), len(planned), state_dir)
            key_data = rng.seed_key_data([s for (_, s, _) in meta])
            # A sweep splits its rows over the devices (the mesh), not each row's envs.
            config = dataclasses.replace(spec.config, devices=1)
            execution = ExecutionPlan.for_run(spec.env, config, compiler_options=plan.compiler_options)
            if mesh is not None:  # rows split over devices: a program XLA partitions
                execution = execution.partitioned(mesh.devices.size)
            trainer = Trainer(spec.env, config, plan=execution)
            group = GroupRunner(trainer, len(meta), mesh, plan.eval_episodes, plan.n_last)
            budget = {"steps": f"{trainer.steps_per_env:,} steps each (total_steps {spec.config.total_steps:,})",
                      "run_episodes": f"until {spec.config.total_episodes:,} episodes a row"
                      }.get(trainer.budget, f"{spec.config.nepisodes} episodes")
            log(f"group {g + 1}/{len(planned)} [{label}]: {len(p.configs)} configs × {len(plan.seeds)} seeds × "
                f"{spec.config.n_envs} envs, {budget} ≤ {spec.config.nsteps} steps")
            hooks: dict[str, Any] = {}
            if carries:
                # The carry is saved with the group's rows only: the padding rows follow this mesh's device
                # count, and a sweep resumed on another count pads them again (repeating the last row as a fresh
                # carry's padding does; they are dropped from every answer).
                def restore(template: Callable[[], Any], g: int = g, n: int = len(meta),
                            padded: int = group.n_padded) -> tuple[Any, int] | None:
                    if not os.path.exists(state.group_carry_path(state_dir, g)):
                        return None  # nothing saved: the template is not traced
                    got = state.load_group_carry(state_dir, fingerprint, g, _rows(template(), n))
                    if got is not None:
                        log(f"  going on from chunk {got[1]} of {trainer.max_chunks()} (saved in "
                            f"{state.group_carry_path(state_dir, g)})")
                        got = (_rows(got[0], padded), got[1])
                    return got

                def save_carry(carry: Any, chunks_done: int, g: int = g, n: int = len(meta)) -> None:
                    state.save_group_carry(state_dir, fingerprint, g, _rows(carry, n), chunks_done)

                hooks = {"restore": restore, "checkpoint": save_carry, "checkpoint_seconds": checkpoint_seconds}
            try:
                metrics = group.run(key_data, _stack(p.agent_list), _stack(p.env_list), progress, plan.max_seconds,
                                    stop=should_stop, callbacks=callbacks, **hooks)
            except SweepInterrupted as err:
                partial = None if err.partial is None else (g, *err.partial[1:])
                raise SweepInterrupted(len(saved), len(planned), state_dir, partial) from None
            saved[g] = {"metrics": metrics, "compile_seconds": group.compile_seconds,
                        "run_seconds": group.run_seconds, "eval_seconds": group.eval_seconds,
                        "start_chunk": group.start_chunk, "restored_env_steps": group.restored_env_steps,
                        "complete": group.complete,
                        "slot_steps": group.slot_steps}
            if state_dir is not None and jax.process_index() == 0:
                state.save_checkpoint(state_dir, fingerprint, plan, saved)
                if carries:  # the metrics are saved: the carry is no longer needed
                    state.drop_group_carry(state_dir, g)
        done = saved[g]
        metrics = done["metrics"]
        steps = int(metrics["env_steps"].astype(np.int64).sum())
        timed = steps - int(done.get("restored_env_steps", 0))  # this process's steps, those its seconds ran
        slots = float(done.get("slot_steps", 0.0))
        timings.append({"group": g, "static": dict(static), "rows": len(meta), "n_envs": spec.config.n_envs,
                        "compile_seconds": done["compile_seconds"], "run_seconds": done["run_seconds"],
                        "eval_seconds": done.get("eval_seconds", 0.0),
                        # A group resumed from its saved carry: its env steps include the chunks run before,
                        # its seconds do not (they were another process's).
                        **({"resumed_after_chunk": int(done["start_chunk"])} if done.get("start_chunk") else {}),
                        "env_steps": steps, "env_steps_per_second": timed / max(done["run_seconds"], 1e-9),
                        "env_slots": slots, "useful_share": steps / slots if slots else None,
                        "complete": done["complete"]})
        log(f"  compiled in {done['compile_seconds']:.1f} s; {timed:,} env steps in {done['run_seconds']:.1f} s "
            f"({timed / max(done['run_seconds'], 1e-9):,.0f} steps/s)"
            + (f", {steps - timed:,} more restored from chunk {done['start_chunk']}" if steps != timed else "")
            + (f"; {steps / slots:.1%} of the env slots useful" if slots else "")
            + f"; evaluated in {done.get('eval_seconds', 0.0):.1f} s")
        for r, (i, s, ap) in enumerate(meta):
            row: dict[str, Any] = {"config": i, "seed": s, "group": g}
            row.update(plan.checked[i])
            row.update({k: float(getattr(ap, k)) for k in rules(AgentParams)})
            for m, values in metrics.items():
                v = values[r]
                row[m] = int(v) if np.issubdtype(values.dtype, np.integer) else float(v)
            rows.append(row)
    rows.sort(key=lambda r: (r["config"], r["seed"]))
    target = getattr(planned[0].spec.env, "learning_target", None) if planned else None
    return SweepResult(plan.env_id, plan.swept, rows, timings, time.perf_counter() - t_all, ranking(target))
