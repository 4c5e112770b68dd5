"""What a training run produced: :class:`TrainResult` (host arrays) and its :meth:`~TrainResult.summary`.

The summary holds the seed's figures (highest cumulated reward, overall mean length, mean of the 100 longest
episodes), timings, the execution plan the run used, the greedy evaluation, and how many evaluated tables reach
the task's declared learning target (:class:`jaxrobo.task.env.LearningTarget`: the task says what "learned" means,
not the trainer). Every "best" it picks (the best 100-episode window, the best table) follows that target's
direction (:func:`jaxrobo.task.env.ranking`): for a minimum-time task the shortest episodes, not the longest; the
seed's ``best_100_mean_length`` keeps its meaning (the longest) for the records that compare with it.
:func:`jaxrobo.io.results.save_run` writes it all to a run directory.

Public surface: :class:`TrainResult`.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from jaxrobo.tabular.learner import AgentParams
from jaxrobo.task.env import LearningTarget, Ranking, ranking
from jaxrobo.training.trainer import TrainConfig

#: The seed's "best 100": each env's 100 longest episodes, its last 100 and its best 100-episode window.
BEST = 100


@dataclasses.dataclass
class TrainResult:
    """What a run produced, as host arrays, with the seed's summary figures."""

    env_id: str
    config: TrainConfig
    agent_params: AgentParams
    returns: np.ndarray  # [n_envs, nepisodes] (Fortran order where fewer were recorded: pad_columns)
    lengths: np.ndarray
    terminated: np.ndarray
    epsilon: np.ndarray  # [nepisodes]
    nan_episodes: np.ndarray  # [n_envs]
    env_steps: int
    #: ``[n_envs or 1, n_tables, n_states, n_actions]``. May be given as the tables' host copy of their nonzero
    #: entries (:class:`jaxrobo.training.nonzero_copy.NonzeroCopy`, ``tables``): made dense when first read.
    q: np.ndarray
    compile_seconds: float
    run_seconds: float
    eval_returns: np.ndarray | None = None  # [eval_envs, eval_episodes]
    eval_lengths: np.ndarray | None = None
    #: Whether each of those episodes arrived (``[eval_envs, eval_episodes]``), for a task whose learning target
    #: is a ``success_rate`` (:func:`jaxrobo.training.driver.evaluate_tables`); None otherwise.
    eval_success: np.ndarray | None = None
    selected: dict[str, Any] | None = None  # the best evaluated table, re-evaluated on fresh episodes
    #: False when ``should_stop`` ended the run early: the records hold the episodes finished so far
    #: (``episodes_done`` per env), there is no evaluation, and the carry at ``chunks_done`` goes on from there.
    complete: bool = True
    chunks_done: int = 0
    episodes_done: np.ndarray | None = None  # [n_envs] finished episodes per env
    #: The task's declared target (:class:`jaxrobo.task.env.LearningTarget`; None: no target), for :meth:`summary`.
    learning_target: LearningTarget | None = None
    plan: str | None = None  # repr of the run's ExecutionPlan (how it ran; the values do not depend on it but for
    # the device splits docs/scaling.md names)
    #: Env steps the carry had already run when this process restored it (``--resume``): ``env_steps`` counts
    #: them, the speed does not (they were run, and timed, by an earlier process).
    restored_env_steps: int = 0
    #: Which table the finished run kept (:meth:`jaxrobo.training.trainer.Trainer.final_table`: 0 the final one,
    #: k the snapshot at ``1 - k * SNAPSHOT_SPACING`` of the budget); None without ``snapshots``.
    final_table_choice: int | None = None

    #: The chunk the carry started from (0, or the checkpoint's on a resume).
    start_chunk: int = 0
    eval_seconds: float = 0.0
    #: Every env's finished episodes, recorded or not (under a run-wide budget an env may finish more than the
    #: ``nepisodes`` it records).
    episodes_finished: int | None = None
    budget: str = "episodes"  # jaxrobo.training.trainer.Trainer.budget
    #: The learning-target checks this process ran (``{"chunks", "score", "confirmed"}`` each, in order), None
    #: when the run does not check (:meth:`jaxrobo.training.trainer.Trainer.target_every`); ``target_every`` their
    #: spacing in chunks; ``target_met_chunk`` the chunk count at which the target held and the run stopped.
    target_checks: list | None = None
    target_every: int = 0
    target_met_chunk: int | None = None
    target_check_seconds: float = 0.0
    #: Wall time of the checkpoint saved after the last chunk, before the evaluation (0: none was saved then; one
    #: written in a thread beside the evaluation, :class:`jaxrobo.training.checkpoint.SaveInThread`, its start).
    checkpoint_seconds: float = 0.0
    #: Wall time of the carry's records and tables copied to the host after the evaluation (this result's arrays):
    #: part of a run's writing (at 1,048,576 envs on an H200, 6.1 s for 8 GB of tables and 3 GB of records).
    copy_seconds: float = 0.0
    #: The records' per-env and per-column parts computed on the device (:mod:`jaxrobo.training.record_parts`, host
    #: arrays), from which :meth:`summary` and ``episode_stats.csv`` take the same floats with fewer sorts; None:
    #: computed from the records here.
    record_parts: dict[str, np.ndarray] | None = None

    @property
    def tables(self) -> Any:
        """``q`` as it was given: an array, or its :class:`~jaxrobo.training.nonzero_copy.NonzeroCopy` (written to a
        file block by block without the dense array, :func:`jaxrobo.io.results.write_tables`)."""
        return self.__dict__["q"]

    @property
    def steps_per_second(self) -> float:
        """Env steps run by this process per second of its run time (restored steps left out)."""
        return (self.env_steps - self.restored_env_steps) / max(self.run_seconds, 1e-9)
    @property
    def slot_steps(self) -> int:
        """Env slots the batch stepped: chunks run (since the start) × chunk steps × envs."""
        return int(self.chunks_done) * int(self.config.chunk_steps) * int(self.config.n_envs)

    @property
    def useful_share(self) -> float:
        """Useful env steps (those counting towards the budget) / env slots stepped."""
        return self.env_steps / self.slot_steps if self.slot_steps else 0.0

    def all_recorded(self) -> bool:
        """Every record slot holds an episode (a complete run under the episode budget): :meth:`recorded` is
        None."""
        done = self.episodes_done
        return done is None or bool(np.all(np.asarray(done) >= self.returns.shape[1]))

    def recorded(self, columns: int | None = None) -> np.ndarray | None:
        """``[n_envs, nepisodes]`` mask of the record slots that hold an episode, or None when all do (a complete
        run under the episode budget). ``columns``: only the mask's first columns (the recorded slots are each
        env's first ones)."""
        if self.all_recorded():
            return None
        n = self.returns.shape[1] if columns is None else columns
        return np.arange(n)[None, :] < np.asarray(self.episodes_done)[:, None]

    def summary(self) -> dict[str, Any]:
        """The seed's figures (highest cumulated reward, overall mean length, mean of the best 100), per run, and
        how many evaluated tables reach the task's declared learning target (``learning_target``)."""
        rank = ranking(self.learning_target)
        if self.record_parts is not None:
            figures = _figures_from_parts(self.record_parts, self.returns, self.episodes_done,
                                          self.all_recorded(), rank)
        else:
            figures = self._figures(rank)
        figures["best_ranked_by"] = rank.words
        c = self.config
        out = {
            "env_id": self.env_id,
            "agent": c.agent,
            "n_envs": c.n_envs,
            "nepisodes": c.nepisodes,
            "budget": self.budget,
            **({"total_steps": c.total_steps} if c.total_steps else {}),
            **({"total_episodes": c.total_episodes} if c.total_episodes else {}),
            **figures,
            "physics_nan_episodes": int(self.nan_episodes.sum()),
            "env_steps": int(self.env_steps),
            "env_slots": self.slot_steps,
            "useful_share": round(self.useful_share, 4),
            "compile_seconds": round(self.compile_seconds, 3),
            "run_seconds": round(self.run_seconds, 3),
            "eval_seconds": round(self.eval_seconds, 3),
            **({"checkpoint_seconds": round(self.checkpoint_seconds, 3)} if self.checkpoint_seconds else {}),
            "env_steps_per_second": round(self.steps_per_second, 1),
        }
        if self.episodes_finished is not None:
            out["episodes_finished"] = int(self.episodes_finished)
            out["episodes_recorded"] = int(np.minimum(self.episodes_done, self.returns.shape[1]).sum()) \
                if self.episodes_done is not None else int(self.returns.size)
        if self.start_chunk:
            out["resumed_after_chunk"] = int(self.start_chunk)
        if self.restored_env_steps:
            out["restored_env_steps"] = int(self.restored_env_steps)
            out["env_steps_this_process"] = int(self.env_steps - self.restored_env_steps)
        if self.final_table_choice is not None:
            out["final_table_choice"] = int(self.final_table_choice)
        if self.target_checks is not None:
            out["target_every_chunks"] = int(self.target_every)
            out["target_checks"] = len(self.target_checks)
            out["target_check_seconds"] = round(self.target_check_seconds, 3)
            out["target_met_in_training"] = self.target_met_chunk is not None
            if self.target_met_chunk is not None:
                out["target_met_at_chunk"] = int(self.target_met_chunk)
                out["target_met_at_env_steps"] = int(self.env_steps)
                out["target_met_at_run_seconds"] = round(self.run_seconds, 3)
            if self.target_checks:
                out["target_last_check_score"] = float(self.target_checks[-1]["score"])
        target = self.learning_target
        if target is not None:
            out["learning_target"] = target.description
        if self.plan is not None:
            out["execution_plan"] = self.plan
        if self.eval_lengths is not None and self.eval_lengths.size:
            out["eval_mean_length"] = float(self.eval_lengths.mean())
            out["eval_mean_return"] = float(self.eval_returns.mean())
            per_table = {"mean_length": self.eval_lengths, "mean_return": self.eval_returns}
            if self.eval_success is not None and self.eval_success.size:
                per_table["success_rate"] = self.eval_success
                out["eval_success_rate"] = float(self.eval_success.mean())
            # The best table by the task's target (the longest only where longer is better), and its figures.
            best = rank.best_table(per_table)
            out["eval_best_table"] = best
            out["eval_best_table_mean_length"] = float(self.eval_lengths[best].mean())
            out["eval_best_table_mean_return"] = float(self.eval_returns[best].mean())
            if "success_rate" in per_table:
                out["eval_best_table_success_rate"] = float(self.eval_success[best].mean())
            if target is not None and target.metric in per_table:
                score = per_table[target.metric].astype(np.float64).mean(axis=1)
                out[f"eval_share_of_tables_{target.name}"] = float(target.reached(score).mean())
        if self.selected is not None:
            out["selected_table"] = self.selected["table"]
            out["selected_table_fresh_mean_length"] = float(self.selected["lengths"].mean())
            out["selected_table_fresh_mean_return"] = float(self.selected["returns"].mean())
        return out

    def _figures(self, rank: Ranking) -> dict[str, float]:
        """The seed's figures and the best window (:meth:`summary`), from the records."""
        returns, lengths, mask = self.returns, self.lengths, None
        if not self.all_recorded():  # no env recorded past the widest one's episodes: the figures need no more
            width = max(min(int(np.max(self.episodes_done)), returns.shape[1]), 1)  # columns (nor its mask)
            mask, returns, lengths = self.recorded(width), returns[:, :width], lengths[:, :width]
        if mask is None:
            # Each env's 100 longest (a sort of each row: most of this at a million envs), block by block.
            def longest(a: int, b: int) -> np.ndarray:
                return np.sort(lengths[a:b].astype(np.float64), axis=1)[:, -BEST:].mean(axis=1)

            best100 = np.concatenate(over_env_blocks(returns.shape[0], longest))
            figures = {"highest_reward_mean": float(returns.max(axis=1).mean()),
                       "highest_reward_max": float(returns.max()),
                       "overall_mean_length": float(lengths.astype(np.float64).mean()),
                       "best_100_mean_length": float(best100.mean()),
                       "final_100_mean_return": float(returns[:, -BEST:].mean())}
        else:
            figures = _masked_figures(returns, lengths, mask)
        figure = returns if rank.episode_figure == "return" else lengths
        figures[f"best_100_window_mean_{rank.episode_figure}"] = best_window(figure, mask, rank)
        return figures


def _q(result: TrainResult) -> np.ndarray:
    q = result.__dict__["q"]
    if not isinstance(q, np.ndarray) and hasattr(q, "dense"):  # a NonzeroCopy: dense from its first read on
        q = result.__dict__["q"] = q.dense()
    return q


def _set_q(result: TrainResult, q: Any) -> None:
    result.__dict__["q"] = q


# ``q`` read through a property (dataclasses sets it in __init__ through the setter): a 1 M-env run's 8 GB of tables
# are made dense only if something reads them, not to write qtables.npz.
TrainResult.q = property(_q, _set_q, doc="The learner's tables, dense when read.")  # type: ignore[assignment]


def _no_figures() -> dict[str, float]:
    """The seed's figures of a run in which no env recorded an episode: NaN each."""
    return dict.fromkeys(("highest_reward_mean", "highest_reward_max", "overall_mean_length", "best_100_mean_length",
                          "final_100_mean_return"), float("nan"))


def _figures_from_parts(parts: dict[str, np.ndarray], returns: np.ndarray, episodes_done: np.ndarray | None,
                        all_recorded: bool, rank: Ranking) -> dict[str, float]:
    """:meth:`TrainResult._figures` from the records' parts (:func:`jaxrobo.training.record_parts.parts`): the same
    floats. Lengths are whole numbers, so their sums (an env's 100 longest, its windows, all of them) are exact in
    any order and a mean is that sum divided once; maxima are exact; the returns averaged are the ones the records
    give, in the same order. The best window of float returns (a task ranked by return) is summed here."""
    n_envs, slots = returns.shape
    count = np.full(n_envs, slots) if all_recorded else np.minimum(np.asarray(episodes_done), slots)
    has = count > 0
    if not has.any():
        figures = _no_figures()
    else:
        highest, k = parts["highest"], np.minimum(count, BEST)
        length_sum = int(np.asarray(parts["length_sum"]).sum(dtype=np.int64))
        last = parts["last_returns"]  # each env's last k returns first, in order: env after env as the records give
        final = (returns[:, -BEST:].mean() if all_recorded  # (float32, as numpy sums that view)
                 else last[np.arange(last.shape[1])[None, :] < k[:, None]].astype(np.float64).mean())
        # (all recorded: float32's mean of each env's maximum, as numpy gives it; else float64 over the envs with any)
        mean_highest = highest.mean() if all_recorded else highest[has].astype(np.float64).mean()
        figures = {"highest_reward_mean": float(mean_highest),
                   "highest_reward_max": float(highest[has].max()),
                   "overall_mean_length": float(np.float64(length_sum) / int(count.sum())),
                   "best_100_mean_length": float(np.mean(parts["top_sum"][has].astype(np.float64) / k[has])),
                   "final_100_mean_return": float(final)}
    if rank.episode_figure == "return":
        width = slots if all_recorded else max(int(count.max()), 1)
        mask = None if all_recorded else np.arange(width)[None, :] < count[:, None]
        figures["best_100_window_mean_return"] = best_window(returns[:, :width], mask, rank)
    else:
        window = np.where(count >= BEST, BEST, np.maximum(count, 1))
        kept = np.asarray(parts["window_sum"])[has].astype(np.float64) / window[has]
        figures["best_100_window_mean_length"] = float(np.mean(kept)) if kept.size else float("nan")
    return figures


def best_window(figure: np.ndarray, mask: np.ndarray | None, rank: Ranking, window: int = BEST) -> float:
    """The best ``window``-episode moving mean of ``figure`` (``[n_envs, episodes]``) in each env, best by
    ``rank``'s direction, averaged over envs; an env with fewer recorded episodes than ``window`` gives the
    mean of all of them, one with none (``mask``: the recorded slots; None: all) is left out."""
    figure = np.asarray(figure)
    counts = np.full(figure.shape[0], figure.shape[1]) if mask is None else np.asarray(mask).sum(axis=1)

    def block(a: int, b: int) -> np.ndarray:
        # The recorded slots are each env's first ones (``TrainResult.recorded``): an env with n of them has its
        # windows end at slots w..n of the prefix sums (w = min(window, n)); one with fewer than ``window`` has
        # one window, all of them. Whole blocks at once, no loop over envs or over their counts (a loop over the
        # distinct counts held Python's lock: 5.0-5.7 s at 1,048,576 envs on an H200 host, whatever the threads).
        # The prefix sums up to a slot do not depend on the slots after it, so every window's mean is the one
        # summed over that env's recorded slots alone.
        c = counts[a:b]
        sums = np.cumsum(np.concatenate([np.zeros((b - a, 1)), figure[a:b].astype(np.float64)], axis=1), axis=1)
        best = np.full(b - a, np.nan)
        few = (c > 0) & (c < window)
        best[few] = np.take_along_axis(sums[few], c[few, None], axis=1)[:, 0] / c[few]
        if figure.shape[1] >= window:
            means = (sums[:, window:] - sums[:, :-window]) / window  # the window ending at slot window + i
            inside = np.arange(means.shape[1])[None, :] <= (c - window)[:, None]
            means = np.where(inside, means, -np.inf if rank.higher else np.inf)
            many = c >= window
            best[many] = (means.max(axis=1) if rank.higher else means.min(axis=1))[many]
        return best

    best = np.concatenate(over_env_blocks(figure.shape[0], block)) if figure.shape[0] else np.zeros(0)
    kept = best[counts > 0]
    return float(np.mean(kept)) if kept.size else float("nan")


def over_env_blocks(n_envs: int, fn: Callable[[int, int], Any], *, threads: int | None = None) -> list:
    """``[fn(a, b) for each block [a, b) of FIGURE_BLOCK_ENVS envs]``, in order, the blocks computed by a thread
    per usable core (numpy's sorts, partitions and reductions release Python's lock). Each figure's per-env
    values are row by row, so a block's are the same whichever thread computes it, and the reductions over
    every env run once on the blocks put back together: the numbers do not depend on the thread count. At
    1,048,576 envs x 330 recorded episodes the summary took 7.1 s of an H200 host's one core."""
    from jaxrobo.core import environ

    starts = list(range(0, n_envs, FIGURE_BLOCK_ENVS))
    ends = [min(a + FIGURE_BLOCK_ENVS, n_envs) for a in starts]
    return environ.in_threads(fn, starts, ends, threads=threads, name="jaxrobo-figures")


#: Envs per block of :func:`_masked_figures`: a block's float64 temporaries are memory the allocator reuses, where
#: float64 copies of the whole ``[envs, episodes]`` records were fresh pages (seconds at 65,536 envs).
FIGURE_BLOCK_ENVS = 4096


def _masked_figures(returns: np.ndarray, lengths: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """The seed's figures over the recorded episodes only (envs with different numbers of episodes: a run-wide
    budget, or a stopped run); an env with none recorded is left out."""
    has = mask.any(axis=1)
    if not has.any():
        return _no_figures()
    # Vectorised over blocks of envs (a Python loop over envs took seconds at 65,536 envs). The recorded slots are
    # each env's first ones (TrainResult.recorded): an env's last k = min(100, count) episodes are the slots
    # [count - k, count). Lengths are whole numbers, so the sum of an env's 100 longest, and of all of them, is
    # exact in any order; each figure is the float64 value a reduction over the whole arrays gives.
    count = mask.sum(axis=1)
    k = np.minimum(count, BEST)
    n_envs, width = mask.shape
    slots = np.arange(width)[None, :]
    whole = np.issubdtype(lengths.dtype, np.integer)

    def block(a: int, b: int) -> tuple:
        m, r, ln = mask[a:b], returns[a:b], lengths[a:b]
        highest = np.where(m, r, -np.inf).max(axis=1).astype(np.float64)
        kept = np.where(m, ln.astype(np.float64), -np.inf)
        top = kept if width <= BEST else np.partition(kept, width - BEST, axis=1)[:, -BEST:]
        best_sum = np.where(np.isfinite(top), top, 0.0).sum(axis=1)
        last = (slots >= (count[a:b] - k[a:b])[:, None]) & (slots < count[a:b, None])
        # (the returns of each env's last k episodes, env by env; the recorded lengths' sum, exact in int64)
        lengths_part = int(ln[m].sum(dtype=np.int64)) if whole else ln[m].astype(np.float64)
        return highest, best_sum, r[last].astype(np.float64), lengths_part

    highest, best_sum, last_returns, lengths_parts = (list(x) for x in zip(*over_env_blocks(n_envs, block)))
    highest, best_sum, last_returns = np.concatenate(highest), np.concatenate(best_sum), np.concatenate(last_returns)
    length_sum, recorded_lengths = (sum(lengths_parts), None) if whole else (0, lengths_parts)
    highest, best100 = highest[has], best_sum[has] / k[has]
    overall = np.float64(length_sum) / int(count.sum()) if whole else np.concatenate(recorded_lengths).mean()
    return {"highest_reward_mean": float(highest.mean()), "highest_reward_max": float(highest.max()),
            "overall_mean_length": float(overall), "best_100_mean_length": float(np.mean(best100)),
            "final_100_mean_return": float(last_returns.mean())}
