"""Run directories: what ``jaxrobo train`` writes and ``jaxrobo plot`` reads (the seed's ``training_results``).

A run directory holds:

=======================  =====================================================================================
``config.yaml``          the resolved configuration (env options and params, learner params, loop settings)
``episodes.csv``         ``env,episode,return,length,terminated,epsilon`` - one row per env and episode (the
                         first ``max_csv_envs`` envs; every env is in ``records.npz``)
``episode_stats.csv``    per episode over all envs: mean, std, 10th/50th/90th percentile of return and length
``records.npz``          every env's ``returns``, ``lengths``, ``terminated``, and ``epsilon`` per episode
``summary.json``         the seed's summary figures and the run's timing
``qtables.npz``          ``q [n_envs, n_tables, n_states, n_actions]`` and the discretiser (``low``, ``width``,
                         ``bins``, ``edges_<i>``) - plain arrays, no pickle; read back, checked against the
                         config's (:func:`check_saved_discretiser`)
``eval.csv``             greedy evaluation: ``table,episode,return,length`` (when evaluated)
``tensorboard/``         TensorBoard scalars per episode (mean return, mean length, epsilon)
``status.json``          ``{"status": "running" | "interrupted" | "complete", ...}``: an interrupted run also
                         says how far it got (``chunks_done``, ``episodes_done_min``) and how to go on
                         (``resume``: the command line)
``checkpoint.npz``       only in an unfinished run: the whole training carry, from which ``jaxrobo train
                         --resume DIR`` goes on (format: :func:`jaxrobo.training.checkpoint.save_checkpoint`),
                         its tables in ``checkpoint.tables.<id>.npz`` and its episode records in
                         ``checkpoint.records.<id>.npz`` beside it, laid out as ``qtables.npz`` and
                         ``records.npz`` (a finished run's are those files, linked, not written again)
=======================  =====================================================================================

A complete run is written into a hidden sibling and renamed into place (:mod:`jaxrobo.io.rundir`), so a directory
whose status is ``complete`` has all of its files. An interrupted run holds ``config.yaml``, ``status.json``,
``checkpoint.npz`` and the episodes finished so far (``episodes.csv``, ``records.npz`` with ``episodes_done``
per env, ``episode_stats.csv`` over the episodes every env finished); no tables, summary or evaluation.
"""
from __future__ import annotations

import csv
import json
import math
import os
import re
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import numpy as np
import yaml

from jaxrobo.io.npz import write_npz_deflated
from jaxrobo.tabular.discretise import Discretiser

EPISODE_COLUMNS = ("env", "episode", "return", "length", "terminated", "epsilon")
STAT_COLUMNS = ("episode", "return_mean", "return_std", "return_p10", "return_p50", "return_p90",
                "length_mean", "length_std", "length_p10", "length_p50", "length_p90", "epsilon")


def write_config(out_dir: str, config: dict[str, Any]) -> None:
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "config.yaml"), "w") as f:
        yaml.safe_dump(config, f, sort_keys=False)


def write_episodes(out_dir: str, returns: np.ndarray, lengths: np.ndarray, terminated: np.ndarray,
                   epsilon: np.ndarray, max_csv_envs: int = 1024, episodes_done: np.ndarray | None = None,
                   order_stats: dict[str, np.ndarray] | None = None,
                   link: str | Callable[[], str | None] | None = None) -> list:
    """Per-episode records: CSV rows for the first ``max_csv_envs`` envs, all envs in ``records.npz``, and stats.

    ``episodes_done`` (recorded episodes per env: an interrupted run, or a run-wide budget): only those get CSV
    rows, ``records.npz`` keeps the count, and each episode index's stats cover the envs that recorded it.
    Returns those stats (:func:`episode_stats`' columns, ``order_stats`` its percentiles' parts where the device
    computed them), for TensorBoard's per-episode scalars.

    ``link``: a file this process wrote with these records laid out as ``records.npz`` (:func:`records_members`:
    the closing checkpoint's, :func:`jaxrobo.training.checkpoint.save_checkpoint`), or a function giving it (or
    None), called once the CSV is written; hard-linked as ``records.npz`` instead of writing the records again,
    where its arrays' names, shapes and dtypes are those the records give and the file system allows a link."""
    os.makedirs(out_dir, exist_ok=True)
    returns, lengths = np.atleast_2d(returns), np.atleast_2d(lengths)
    terminated = np.atleast_2d(terminated)
    n_envs, n_ep = returns.shape
    done = np.full(n_envs, n_ep) if episodes_done is None else np.minimum(np.asarray(episodes_done), n_ep)
    # The stats are computed while the records are written (at 1,048,576 envs on an H200 host, 2.9 s of stats
    # after 1.9 s of records.npz, one after the other): both release Python's lock for most of their work.
    with ThreadPoolExecutor(1, thread_name_prefix="jaxrobo-stats-all") as pool:
        stats_future = pool.submit(episode_stats, returns, lengths, epsilon, done, order_stats=order_stats)
        with open(os.path.join(out_dir, "episodes.csv"), "w", newline="") as f:
            f.write(",".join(EPISODE_COLUMNS) + "\r\n")  # the csv module's dialect: nothing here needs quoting
            f.write(episode_rows(returns, lengths, terminated, epsilon, done, max_csv_envs))
        members = records_members(returns, lengths, terminated, epsilon, episodes_done)
        path = os.path.join(out_dir, "records.npz")
        linked = link() if callable(link) else link
        if linked is None or not _same_members(linked, members) or not _linked(linked, path):
            write_npz_deflated(path, **members)
        stats = stats_future.result()
    with open(os.path.join(out_dir, "episode_stats.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(STAT_COLUMNS)
        for row in zip(*stats):
            w.writerow([int(row[0])] + [f"{v:.6g}" for v in row[1:]])
    return stats


def records_members(returns: np.ndarray, lengths: np.ndarray, terminated: np.ndarray, epsilon: np.ndarray,
                    episodes_done: np.ndarray | None = None, *, width: int | None = None) -> dict[str, np.ndarray]:
    """The arrays of ``records.npz``, in its order: ``returns``, ``lengths``, ``terminated`` (``[n_envs, kept]``),
    ``epsilon`` (``[kept]``) and, given ``episodes_done`` (recorded episodes per env, at most ``width``), that
    count; ``kept`` is the most episodes any env recorded (``width`` without ``episodes_done``): a run that stopped at
    its learning target recorded a few of its slots, and the empty rest is most of the bytes. ``width``: the
    records' slots per env (default ``returns.shape[1]``), where the arrays given hold only their first columns
    (cut by :func:`jaxrobo.training.checkpoint.cut_records`); ValueError where they hold fewer than ``kept``."""
    width = returns.shape[1] if width is None else width
    done = None if episodes_done is None else np.minimum(np.asarray(episodes_done), width)
    kept = (width if done is None else int(done.max())) if returns.shape[0] else 0
    if kept > min(x.shape[1] for x in (returns, lengths, terminated)):
        raise ValueError(f"records of {returns.shape[1]} columns given where {kept} were recorded")
    extra = {} if done is None else {"episodes_done": done}
    return dict(returns=returns[:, :kept], lengths=lengths[:, :kept], terminated=terminated[:, :kept],
                epsilon=np.asarray(epsilon)[:kept], **extra)


def _same_members(path: str, members: dict[str, np.ndarray]) -> bool:
    """Whether the ``.npz`` at ``path`` holds arrays of ``members``' names, in that order, shapes and dtypes."""
    from jaxrobo.io.npz import NpzError, member_headers

    try:
        return list(member_headers(path).items()) == [(name, (x.shape, x.dtype)) for name, x in members.items()]
    except NpzError:
        return False


def _linked(source: str, path: str) -> bool:
    """``source`` hard-linked as ``path``; False where the file system refuses it."""
    try:
        os.link(source, path)
        return True
    except OSError:
        return False


def episode_rows(returns: np.ndarray, lengths: np.ndarray, terminated: np.ndarray, epsilon: np.ndarray,
                 done: np.ndarray, max_envs: int) -> str:
    """The rows of ``episodes.csv`` (:data:`EPISODE_COLUMNS`) as one text: env by env, the first ``done[env]``
    episodes of the first ``max_envs`` envs, floats to 6 significant digits, each line ended as the csv module
    ends it. One formatting call per row: writing them through ``csv.writer`` took most of a large run's
    writing (hundreds of thousands of rows)."""
    n = min(returns.shape[0], max_envs)
    mask = np.arange(returns.shape[1])[None, :] < np.asarray(done[:n])[:, None]
    env, episode = np.nonzero(mask)
    columns = (env.tolist(), episode.tolist(), returns[:n][mask].tolist(), lengths[:n][mask].tolist(),
               terminated[:n][mask].astype(np.int64).tolist(), np.asarray(epsilon)[episode].tolist())
    return "".join(map("%d,%d,%.6g,%d,%d,%.6g\r\n".__mod__, zip(*columns)))


def _percentiles(x: np.ndarray, qs: tuple[int, ...]) -> np.ndarray:
    """``np.percentile(x, q, axis=0)`` for each ``q``, from one partition; each as the call with that one ``q``
    returns it (its dtype: float32 for float32 ``x``)."""
    return np.percentile(x, np.asarray(qs, np.result_type(x.dtype, np.float16)), axis=0)


#: The percentiles of ``episode_stats.csv`` (:data:`STAT_COLUMNS`' ``_p10``, ``_p50``, ``_p90``).
PERCENTILES = (10, 50, 90)

#: Bytes of float64 a block of episode columns holds at most (:func:`episode_stats`): a block's temporaries are
#: then memory the allocator reuses, where copies of the whole ``[envs, episodes]`` records were fresh pages
#: (seconds at 65,536 envs).
STATS_BLOCK_BYTES = 8 << 20

#: Bytes of float64 a block of envs holds in :func:`_masked_moments`. The sums are the same at any size (each block's
#: sum starts from the blocks' before it); fewer, larger blocks take Python's lock fewer times, which counts where
#: the tables' file is deflated beside them: at 1 M envs on an H200 host's 16 cores the returns' means and spreads
#: took 2.8-4.1 s in blocks of 1 MB and 1.3-1.5 s in blocks of 8 MB
#: (``benchmarks/results/h200/moment_blocks_s34.json``); on 2 CPU cores either size takes the same time.
MOMENT_BLOCK_BYTES = 8 << 20


def recorded_per_column(done: np.ndarray, n_ep: int) -> np.ndarray:
    """``[n_ep]``: how many envs recorded each episode column (env ``e`` its first ``done[e]``)."""
    hist = np.bincount(np.minimum(np.asarray(done, np.int64), n_ep), minlength=n_ep + 1)
    return hist[::-1].cumsum()[::-1][1:]  # envs whose count exceeds the column's index


def percentile_ranks(count: np.ndarray, qs: tuple[int, ...] = PERCENTILES) -> tuple[list, np.ndarray]:
    """The positions of ``qs`` among a column's ``count`` values (linear interpolation, as numpy's), and the ranks
    ``[2 * len(qs), columns]`` whose values they lie between: each ``q``'s lower rank, then each ``q``'s upper."""
    count = np.asarray(count, np.int64)
    pos = [(count - 1) * (q / 100.0) for q in qs]
    lo = [np.floor(p).astype(np.int64) for p in pos]
    hi = [np.minimum(r + 1, count - 1) for r in lo]
    return pos, np.stack(lo + hi) if qs else np.zeros((0, count.size), np.int64)


def from_order_statistics(values: np.ndarray, pos: list, ranks: np.ndarray) -> list[np.ndarray]:
    """Each percentile from the float64 values at its two ranks (:func:`percentile_ranks`), the lower one plus the
    share of the step its position takes."""
    values = np.asarray(values, np.float64)
    n = len(pos)
    return [values[i] + (values[n + i] - values[i]) * (pos[i] - ranks[i]) for i in range(n)]


def episode_stats(returns: np.ndarray, lengths: np.ndarray, epsilon: np.ndarray, done: np.ndarray, *,
                  threads: int | None = None, order_stats: dict[str, np.ndarray] | None = None) -> list:
    """The columns of ``episode_stats.csv`` (:data:`STAT_COLUMNS`): per episode index, the mean, spread and
    percentiles over the envs that recorded that episode (``done``: recorded episodes per env). Where every env
    recorded the same number (the episode budget) that is every env; under a run-wide budget the envs differ
    and an index is kept while at least one env recorded it: the mean and spread are ``np.nanmean`` and
    ``np.nanstd`` over the recorded entries (a NaN return left out), the percentiles interpolate between the
    recorded entries sorted (a NaN return among them, last).

    ``order_stats``: under a run-wide budget, ``{"returns", "lengths"}``, each ``[2 * len(PERCENTILES), >= n]``:
    every column's values at the ranks :func:`percentile_ranks` gives for its recorded count, picked from the
    column sorted with its unrecorded entries last (NaN among floats) — computed on the device
    (:mod:`jaxrobo.training.record_parts`); None: partitioned here. The numbers are the same either way.

    The percentiles are computed over blocks of episode columns (:data:`STATS_BLOCK_BYTES`); a block is at least two
    columns wide (numpy folds a lone column's axis away and would sum it in another order). ``threads``: how many
    compute the blocks (default: a usable core each; the numbers are the same for any count)."""
    n_envs = returns.shape[0]
    if n_envs == 0:
        return [np.arange(0)] * len(STAT_COLUMNS)
    done = np.asarray(done)
    equal = bool(np.all(done == done[0]))
    n_ep = int(done[0]) if equal else int(done.max())
    if equal:
        columns = _column_blocks(lambda a, b: _equal_stats(np.ascontiguousarray(returns[:, a:b]),
                                                           np.ascontiguousarray(lengths[:, a:b])),
                                 n_envs, n_ep, threads, len(STAT_COLUMNS) - 2)
        return [np.arange(n_ep), *columns, np.asarray(epsilon)[:n_ep]]
    pos, ranks = percentile_ranks(recorded_per_column(done, n_ep))
    if order_stats is None:
        def block(a: int, b: int) -> list:
            return [_order_statistics(x[:, a:b], done - a, ranks[:, a:b]) for x in (returns, lengths)]

        order_stats = dict(zip(("returns", "lengths"), _column_blocks(block, n_envs, n_ep, threads, 2)))
    columns = []
    for name, x in (("returns", returns), ("lengths", lengths)):
        values = np.asarray(order_stats[name])[:, :n_ep]
        if values.shape != ranks.shape:
            raise ValueError(f"order_stats[{name!r}]: expected {ranks.shape[0]} rows of at least {n_ep} columns, "
                             f"got shape {np.shape(order_stats[name])}")
        columns += [*_masked_moments(x, done, n_ep, threads), *from_order_statistics(values, pos, ranks)]
    return [np.arange(n_ep), *columns, np.asarray(epsilon)[:n_ep]]


def _column_blocks(block: Callable[[int, int], list], n_envs: int, n_ep: int, threads: int | None,
                   n_out: int) -> list[np.ndarray]:
    """``block(a, b)``'s arrays over blocks of episode columns (:data:`STATS_BLOCK_BYTES`), each joined along the
    columns: ``n_out`` arrays."""
    width = max(2, STATS_BLOCK_BYTES // (8 * n_envs))
    starts = list(range(0, n_ep, width))
    if len(starts) > 1 and n_ep - starts[-1] < 2:
        starts.pop()  # the last block takes the lone column
    ends = starts[1:] + [n_ep]
    # The blocks are independent and numpy's reductions and partitions release the GIL: a thread per core. The
    # stats were most of write_episodes (262,144 envs x 123 episodes on 2 CPU cores: 3.4 of 4.0 s; 2.2 s in all
    # with two threads), which took 38.8 s of a 1,048,576-env run's writing on an H200 host. Each block's numbers
    # are the same whichever thread computes it.
    from jaxrobo.core.environ import in_threads

    blocks = in_threads(block, starts, ends, threads=threads, name="jaxrobo-stats")
    return [np.concatenate(c, axis=-1) for c in zip(*blocks)] if blocks else [np.zeros(0)] * n_out


def _equal_stats(returns: np.ndarray, lengths: np.ndarray) -> list:
    """:func:`episode_stats`' columns but the first and last, every env having recorded each column (C-ordered
    blocks: a reduction over the envs sums in the order of the memory it reads, and a run's records are
    Fortran-ordered where it recorded fewer episodes than its slots,
    :func:`jaxrobo.training.checkpoint.pad_columns`)."""
    return [returns.mean(0), returns.std(0), *_percentiles(returns, PERCENTILES),
            lengths.mean(0), lengths.std(0), *_percentiles(lengths, PERCENTILES)]


def _order_statistics(x: np.ndarray, done: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """``[len(ranks), columns]``: each column's value at its ranks among its recorded entries (env ``e`` its first
    ``done[e]``; NaN after every number, as a sort puts it), float64, from one partition of each column."""
    mask = np.arange(x.shape[1])[None, :] < done[:, None]
    x = np.where(mask, x.astype(np.float64), np.nan)
    out = np.empty(ranks.shape, np.float64)
    for c in range(x.shape[1]):
        part = np.partition(x[:, c], np.unique(ranks[:, c]))
        out[:, c] = part[ranks[:, c]]
    return out


def _masked_moments(x: np.ndarray, done: np.ndarray, n_ep: int, threads: int | None) -> tuple[np.ndarray, ...]:
    """Each of the first ``n_ep`` columns' mean and spread over its recorded entries (env ``e`` its first ``done[e]``)
    that are numbers: the floats ``np.nanmean`` and ``np.nanstd`` give over the float64 records with NaN in the
    unrecorded slots. Those sum each column over the envs in order (a C-ordered reduction over the first axis);
    here the same sums run over blocks of envs, each block's sum started from the previous blocks' (a block of a
    few columns and every env read column by column was most of a large run's statistics: every row's cache line
    read for a few of its bytes). Threads take groups of columns (a column's sum is its own)."""
    from jaxrobo.core.environ import in_threads, usable_cores

    n_envs = x.shape[0]
    group = max(2, -(-n_ep // max(1, (threads or usable_cores()) * 2)))
    starts = list(range(0, n_ep, group))
    if len(starts) > 1 and n_ep - starts[-1] < 2:
        starts.pop()  # at least two columns (numpy folds a lone column's axis away: another order)
    ends = starts[1:] + [n_ep]

    def columns(a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        if b - a < 2:  # a lone column (n_ep 1): numpy sums it as a line of its own, pairwise
            kept = np.where(np.arange(a, b)[None, :] < done[:, None], x[:, a:b].astype(np.float64), np.nan)
            with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                return np.nanmean(kept, 0), np.nanstd(kept, 0)
        rows = max(1, MOMENT_BLOCK_BYTES // (8 * (b - a)))
        slots = np.arange(a, b)[None, :]

        def blocks():  # the float64 block, zero where not a recorded number, and where it is (None: everywhere)
            for e in range(0, n_envs, rows):
                block = x[e:e + rows, a:b].astype(np.float64, order="C")  # C-ordered: summed row by row
                done_here = done[e:e + rows]
                keep = None if done_here.min() >= b else slots < done_here[:, None]
                if x.dtype.kind == "f":
                    nan = np.isnan(block)
                    if nan.any():
                        keep = ~nan if keep is None else keep & ~nan
                if keep is not None:
                    np.copyto(block, 0.0, where=~keep)
                yield block, keep

        count, total, squares = np.zeros(b - a, np.intp), None, None
        for block, keep in blocks():
            count += block.shape[0] if keep is None else keep.sum(axis=0)
            total = _summed_on(total, block)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = total / count
            for block, keep in blocks():
                np.subtract(block, mean, out=block)
                if keep is not None:
                    np.copyto(block, 0.0, where=~keep)
                squares = _summed_on(squares, np.multiply(block, block, out=block))
            return mean, np.sqrt(squares / count)

    parts = in_threads(columns, starts, ends, threads=threads, name="jaxrobo-moments")
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _summed_on(total: np.ndarray | None, block: np.ndarray) -> np.ndarray:
    """``block``'s rows added in order to ``total`` (None: from its first row; ``block`` is overwritten): a C-ordered
    reduction over the first axis adds row by row, so the blocks of an array summed in turn give the whole array's
    sum (``total`` added to the first row is where a reduction of ``total`` and the rows would start)."""
    if total is not None:
        block[0] += total
    return np.add.reduce(block, axis=0)


#: The members of ``qtables.npz`` besides the discretiser's ``edges_<i>`` (:func:`discretiser_arrays`).
TABLES_MEMBERS = ("q", "low", "width", "bins")


def discretiser_arrays(disc: Discretiser | None) -> dict[str, np.ndarray]:
    """The arrays of ``qtables.npz`` beside ``q``: the discretiser's ``low``, ``width``, ``bins`` and ``edges_<i>``
    (none without a discretiser)."""
    if disc is None:
        return {}
    arrays = {"low": np.asarray(disc.low), "width": np.asarray(disc.width), "bins": np.asarray(disc.bins)}
    for i, e in enumerate(disc.edges or ()):
        arrays[f"edges_{i}"] = np.asarray(e)
    return arrays


def write_tables(out_dir: str, q: np.ndarray, disc: Discretiser | None = None, *, link: str | None = None) -> None:
    """``qtables.npz``: ``q`` and the discretiser's arrays (:func:`discretiser_arrays`). ``link``: a file this
    process wrote with exactly those arrays in this layout (the closing checkpoint's tables,
    :func:`jaxrobo.training.checkpoint.save_checkpoint`), hard-linked instead of writing the tables again; where
    the file system refuses a link, the tables are written."""
    path = os.path.join(out_dir, "qtables.npz")
    if link is None or not _linked(link, path):
        write_npz_deflated(path, q=q if hasattr(q, "npy_pieces") else np.asarray(q), **discretiser_arrays(disc))


def write_summary(out_dir: str, summary: dict[str, Any]) -> None:
    with open(os.path.join(out_dir, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)


def write_eval(out_dir: str, returns: np.ndarray, lengths: np.ndarray) -> None:
    with open(os.path.join(out_dir, "eval.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(("table", "episode", "return", "length"))
        for t in range(returns.shape[0]):
            for i in range(returns.shape[1]):
                w.writerow((t, i, f"{returns[t, i]:.6g}", int(lengths[t, i])))


def write_tensorboard(out_dir: str, stats: list) -> None:
    """Per-episode scalars for TensorBoard, at the end of a run: ``episode_stats.csv``'s ``return_mean``,
    ``length_mean`` and ``epsilon`` (``stats``: :func:`episode_stats`' columns, as :func:`write_episodes` returns
    them); the live scalars of each chunk are the CLI's."""
    from jaxrobo.io.events import ScalarWriter

    try:
        writer = ScalarWriter(os.path.join(out_dir, "tensorboard"), filename_suffix=".episodes")
    except ImportError:  # pragma: no cover - a dependency, but keep runs working without it
        return
    try:
        mean_r, mean_l, epsilon = stats[1], stats[6], stats[11]
        for i in range(mean_r.shape[0]):
            writer.add_scalar("episode/reward_mean", float(mean_r[i]), i)
            writer.add_scalar("episode/length_mean", float(mean_l[i]), i)
            writer.add_scalar("episode/epsilon", float(epsilon[i]), i)
    finally:
        writer.close()


def save_run(out_dir: str, result: Any, run_config: dict[str, Any], disc: Discretiser | None = None,
             summary: dict[str, Any] | Callable[[], dict[str, Any]] | None = None,
             tables: str | Callable[[], str | None] | None = None,
             records: str | Callable[[], str | None] | None = None) -> str:
    """Write everything a :class:`jaxrobo.training.summary.TrainResult` holds into ``out_dir``; returns ``out_dir``.
    ``summary``: ``result.summary()`` where the caller has it already, or a function giving it (called after the
    episode files are written: the caller may be computing it meanwhile), or None: computed here. ``tables``: a file
    holding ``result.q`` as ``qtables.npz`` would (:func:`write_tables`' ``link``), or a function giving it (or
    None), called once everything else is written: the checkpoint that writes that file may still be writing it
    (:class:`jaxrobo.training.checkpoint.SaveInThread`). ``records``: the same for ``records.npz``
    (:func:`write_episodes`' ``link``), called once ``episodes.csv`` is written.

    An interrupted result (``complete`` False) writes its config and the episodes finished so far only. The
    caller writes ``status.json`` (and, for an interrupted run, the checkpoint) and publishes the directory
    (:mod:`jaxrobo.io.rundir`)."""
    write_config(out_dir, run_config)
    if not getattr(result, "complete", True):
        write_episodes(out_dir, result.returns, result.lengths, result.terminated, result.epsilon,
                       episodes_done=result.episodes_done)
        return out_dir
    partial = not result.all_recorded() if hasattr(result, "all_recorded") else False
    parts = getattr(result, "record_parts", None)
    stats = write_episodes(out_dir, result.returns, result.lengths, result.terminated, result.epsilon,
                           episodes_done=result.episodes_done if partial else None,
                           order_stats=None if parts is None or not partial else
                           {"returns": parts["order_returns"], "lengths": parts["order_lengths"]}, link=records)
    write_summary(out_dir, result.summary() if summary is None else summary() if callable(summary) else summary)
    if result.eval_lengths is not None:
        write_eval(out_dir, result.eval_returns, result.eval_lengths)
    write_tensorboard(out_dir, stats)  # the CSV's statistics, not computed again
    write_tables(out_dir, result.tables, disc, link=tables() if callable(tables) else tables)
    return out_dir


def load_config(run_dir: str) -> dict[str, Any]:
    """A run's ``config.yaml`` as a mapping; FileNotFoundError if absent, ConfigError if it is not valid YAML
    or not a mapping whose sections (``env_options``, ``env_params``, ``agent_params``, ``train``) are mappings."""
    from jaxrobo.core.config import ConfigError, load_yaml

    path = os.path.join(run_dir, "config.yaml")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{run_dir}: no config.yaml; is it a jaxrobo run directory?")
    cfg = load_yaml(path)
    for section in ("env_options", "env_params", "agent_params", "train"):
        if cfg.get(section) is not None and not isinstance(cfg[section], dict):
            raise ConfigError(f"{path}: {section} must be a mapping of key: value, got {cfg[section]!r}")
    if "env_id" in cfg and not isinstance(cfg["env_id"], str):
        raise ConfigError(f"{path}: env_id must be a string, got {cfg['env_id']!r}")
    if "preset" in cfg and not isinstance(cfg["preset"], str):
        raise ConfigError(f"{path}: preset must be a string, got {cfg['preset']!r}")
    return cfg


def read_columns(path: str, required: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """A numeric CSV with a header row as ``{column: float array}``.

    ValueError naming the file, and the column or line, when a ``required`` column is missing, a column is named
    twice, a row is short (a truncated file) or a value is not a number. NaN and inf are numbers here: an episode
    of diverged physics records a NaN return, which the plot draws as a gap (:func:`jaxrobo.pictures.plots.smooth`);
    the columns used as indices are checked where they are used (:func:`load_stats`)."""
    return _read_columns(path, required)[0]


def _read_columns(path: str, required: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], list[int]]:
    """:func:`read_columns`' columns and the line of the file each row ends on (a blank line is no row, so the
    row's index alone would name the wrong line)."""
    from jaxrobo.core.config import check_regular

    check_regular(path)  # a FIFO would hang the read, a device never end it
    rows, lines = [], []
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            twice = sorted({name for name in header if header.count(name) > 1})
            if twice:  # a dict row keeps one of the two values: columns of unequal lengths, or the wrong one
                raise ValueError(f"{path}: column(s) {', '.join(map(repr, twice))} named twice in the header")
            missing = [c for c in required if c not in header]
            if missing:
                raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(required)}")
            for row in reader:
                rows.append(row)
                lines.append(reader.line_num)
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a text CSV file ({err})") from None
    except csv.Error as err:
        raise ValueError(f"{path}: not a valid CSV file ({err})") from None
    if not rows:
        raise ValueError(f"{path} has no rows")
    out: dict[str, list[float]] = {name: [] for name in header}
    for line, row in zip(lines, rows):
        if None in row or any(row.get(name) is None for name in header):
            raise ValueError(f"{path} line {line}: expected {len(header)} values ({', '.join(header)}); "
                             "the file is truncated or malformed")
        for name in header:
            try:
                out[name].append(float(row[name]))
            except ValueError:
                raise ValueError(f"{path} line {line}: column {name}={row[name]!r} is not a number") from None
    return {name: np.asarray(values) for name, values in out.items()}, lines


#: The columns of ``episode_stats.csv`` that ``jaxrobo plot`` draws.
PLOTTED_STATS = ("episode", "return_mean", "return_p10", "return_p90", "length_mean", "length_p10", "length_p90")


#: A TensorBoard record longer than this is not one jaxrobo wrote (its scalars are a few hundred bytes).
MAX_TB_RECORD = 1 << 20
#: Bytes read of one event file at most: a run's scalars take kilobytes; a larger file is read up to here.
MAX_TB_FILE = 256 << 20


def read_scalars(logdir: str) -> dict[str, list[tuple[int, float]]]:
    """The scalars of the TensorBoard event files in ``logdir`` (a run's ``tensorboard/``), ``{tag: [(step,
    value), ...]}``, readable while the run writes them: the records a writer has flushed, a record half written
    at the end left out. The files are read as hostile: a record that does not parse or is longer than
    :data:`MAX_TB_RECORD` ends that file's reading, and no more than :data:`MAX_TB_FILE` bytes of a file are read
    (TFRecord framing; tensorboardX's protos)."""
    import struct

    from jaxrobo.io.events import tensorboardx

    tensorboardx()  # the package without PyTorch, before its protos
    from tensorboardX.proto import event_pb2

    out: dict[str, list[tuple[int, float]]] = {}
    if not os.path.isdir(logdir):
        raise FileNotFoundError(f"{logdir}: no TensorBoard folder (was the run started by `jaxrobo train`?)")
    for name in sorted(os.listdir(logdir)):
        path = os.path.join(logdir, name)
        if not (name.startswith("events.") and os.path.isfile(path)):
            continue
        with open(path, "rb") as f:
            data = f.read(MAX_TB_FILE)  # bounded: a hostile or runaway file cannot exhaust the memory
        pos = 0
        while pos + 12 <= len(data):
            (n,) = struct.unpack("<Q", data[pos:pos + 8])
            if n > MAX_TB_RECORD or pos + 12 + n + 4 > len(data):
                break  # not one of ours, or a record being written
            try:
                event = event_pb2.Event.FromString(data[pos + 12:pos + 12 + n])
            except Exception:  # protobuf's DecodeError: a damaged file ends here
                break
            pos += 12 + n + 4
            for v in event.summary.value:
                out.setdefault(v.tag, []).append((int(event.step), float(v.simple_value)))
    return out


#: Largest ``env`` or ``episode`` number read from an ``episodes.csv`` (int32's largest, as a run's counts are).
MAX_CSV_INDEX = 2**31 - 1


def _check_indices(path: str, data: dict[str, np.ndarray], lines: list[int], names: tuple[str, ...]) -> None:
    """ValueError naming the file, line and column where a column of ``names`` is not a whole number in
    0..:data:`MAX_CSV_INDEX` (NaN and inf included)."""
    for name in names:
        col = data[name]
        with np.errstate(invalid="ignore"):
            bad = np.flatnonzero(~((col >= 0) & (col <= MAX_CSV_INDEX) & (col == np.round(col))))
        if bad.size:  # before any cast: 1e300 as an int is garbage, and garbage indexes or sizes an array
            raise ValueError(f"{path} line {lines[bad[0]]}: column {name}={col[bad[0]]:.15g}: expected a whole "
                             f"number in 0..{MAX_CSV_INDEX}")


def load_stats(run_dir: str) -> dict[str, np.ndarray]:
    """Per-episode statistics of a run (from ``episode_stats.csv``, else computed from ``episodes.csv``)."""
    path = os.path.join(run_dir, "episode_stats.csv")
    if os.path.exists(path):
        data, lines = _read_columns(path, PLOTTED_STATS)
        _check_indices(path, data, lines, ("episode",))  # the x axis: a NaN, negative or 1.5 episode is no episode
        return data
    path = os.path.join(run_dir, "episodes.csv")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{run_dir}: no episode_stats.csv or episodes.csv; is it a jaxrobo run directory?")
    data, lines = _read_columns(path, ("env", "episode", "return", "length", "epsilon"))
    _check_indices(path, data, lines, ("env", "episode"))
    env, ep = data["env"].astype(np.int64), data["episode"].astype(np.int64)
    n_env, n_ep = int(env.max()) + 1, int(ep.max()) + 1
    if n_env * n_ep > 10 * env.size + 1_000_000:  # Python ints: no overflow
        raise ValueError(f"{path}: env/episode numbers up to {n_env - 1}/{n_ep - 1} for {env.size} rows; "
                         "the file is malformed")
    r = np.full((n_env, n_ep), np.nan)
    r[env, ep] = data["return"]
    ln = np.full((n_env, n_ep), np.nan)
    ln[env, ep] = data["length"]
    eps = np.zeros(n_ep)
    eps[ep] = data["epsilon"]
    stats = {"episode": np.arange(n_ep), "epsilon": eps}
    for name, x in (("return", r), ("length", ln)):
        stats[f"{name}_mean"] = np.nanmean(x, 0)
        stats[f"{name}_std"] = np.nanstd(x, 0)
        for q in (10, 50, 90):
            stats[f"{name}_p{q}"] = np.nanpercentile(x, q, axis=0)
    return stats


#: Most bytes of a ``summary.json`` read back for its selected table (a hostile file is not read whole).
MAX_SUMMARY_BYTES = 16 << 20


def selected_table(run_dir: str, n_tables: int) -> int:
    """The table a run's greedy evaluation selected (``summary.json``'s ``selected_table``), which ``jaxrobo show``,
    ``export`` and ``sim2sim`` act with by default; 0 where the run has no summary or it names no table of the
    ``n_tables`` (an older, interrupted or hostile run directory)."""
    from jaxrobo.core.config import parse_json

    try:
        if not os.path.isfile(os.path.join(run_dir, "summary.json")):  # nor a FIFO or a device
            return 0
        with open(os.path.join(run_dir, "summary.json"), encoding="utf-8") as f:
            chosen = parse_json(f.read(MAX_SUMMARY_BYTES)).get("selected_table", 0)
    except (OSError, ValueError, AttributeError):
        return 0
    ok = isinstance(chosen, int) and not isinstance(chosen, bool) and 0 <= chosen < n_tables
    return chosen if ok else 0


def load_tables(run_dir: str) -> dict[str, np.ndarray]:
    """A run's ``qtables.npz`` as plain arrays (no pickle); ConfigError naming the file when it is missing,
    truncated, pickled or has no ``q`` of shape ``[n_envs, n_tables, n_states, n_actions]``. The discretiser's
    arrays beside ``q`` are read, not checked: each reader checks them against the discretiser the run's config
    builds (:func:`check_saved_discretiser`), ``q`` against the config (:func:`jaxrobo.training.run.check_tables`)."""
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.npz import member_headers, read_npz

    path = os.path.join(run_dir, "qtables.npz")
    if not os.path.isfile(path):
        raise ConfigError(f"{run_dir}: no qtables.npz; is it a finished jaxrobo run directory?")
    # Headers checked before any data is read (a header claiming 2^40 rows is refused, not allocated); the tables'
    # finiteness is checked per table by the caller (one NaN table must not hide the others), the discretiser's by
    # check_saved_discretiser (naming the field and what was expected).
    arrays = read_npz(path, "the q-tables", finite=False, wanted=lambda name: name in TABLES_MEMBERS
                      or re.fullmatch(r"edges_\d+", name) is not None)
    if "q" not in arrays:
        found = ", ".join(member_headers(path)) or "none"
        raise ConfigError(f"{path}: no array 'q' (found {found})")
    q = arrays["q"]
    if q.ndim != 4 or not np.issubdtype(q.dtype, np.floating):
        raise ConfigError(f"{path}: q must be a float array [n_envs, n_tables, n_states, n_actions], got "
                          f"{q.dtype} of shape {q.shape}")
    if 0 in q.shape:
        raise ConfigError(f"{path}: q of shape {q.shape} holds no table; every axis must be at least 1")
    return arrays


def _listed(x: np.ndarray, most: int = 8) -> str:
    """A vector's values as a list, its first ``most`` and a count of the rest; each as its dtype prints it (a
    float32 in its shortest digits)."""
    more = f", ... ({x.size} values)" if x.size > most else ""
    return "[" + ", ".join(map(str, np.asarray(x).ravel()[:most])) + more + "]"


def check_saved_discretiser(saved: dict[str, np.ndarray], disc: Discretiser, path: str) -> None:
    """The discretiser saved beside ``q`` in a run's ``qtables.npz`` (``saved``: :func:`load_tables`' arrays, read
    from ``path``) against ``disc``, the one the run's env and config build
    (:func:`jaxrobo.tabular.discretise.make_discretiser_for`), before anything uses the tables: every array
    :func:`discretiser_arrays` writes (``low``, ``width``, ``bins``, and ``edges_<i>`` for an ``edges``
    discretiser) present and no other ``edges_<i>``; each of its shape and dtype (``bins`` any integers); finite;
    ``bins`` whole numbers >= 1 whose product is ``q``'s states; and each value that of ``disc``. ConfigError naming
    the file, the field and what was expected otherwise: the tables are then not the config's, and a table read
    through another discretiser acts on the wrong states."""
    from jaxrobo.core.config import ConfigError

    mine = discretiser_arrays(disc)
    dims = len(disc.bins)
    kind = "edges" if disc.edges is not None else "uniform"
    found = ", ".join(name for name in saved if name != "q") or "none"
    for name in mine:
        if name not in saved:
            raise ConfigError(f"{path}: no array {name!r} of the discretiser (found {found}); expected "
                              f"{', '.join(mine)}: the {kind} discretiser the run's config.yaml builds")
    for name in saved:
        if name != "q" and name not in mine:
            raise ConfigError(f"{path}: array {name!r} is no part of the {kind} discretiser the run's config.yaml "
                              f"builds ({dims} dimensions: {', '.join(mine)}); the files are not of one run")
    for name, want in mine.items():
        x = saved[name]
        ints = name == "bins" and x.dtype.kind in "iu"
        if x.shape != want.shape or not (ints or x.dtype == want.dtype):
            if name == "bins" and x.shape == want.shape and x.dtype.kind == "f":
                raise ConfigError(f"{path}: bins={_listed(x)} ({x.dtype}): expected whole numbers >= 1 as "
                                  f"integers, one per observation dimension")
            what = "integers" if name == "bins" else str(want.dtype)
            each = "that dimension's interior edges" if name.startswith("edges_") else "one per observation dimension"
            raise ConfigError(f"{path}: {name} is {x.dtype} of shape {x.shape}, expected {what} of shape "
                              f"{want.shape} ({each}, as the run's config.yaml builds it)")
        if x.dtype.kind == "f" and not np.all(np.isfinite(x)):
            bad = int(x.size - np.count_nonzero(np.isfinite(x)))
            raise ConfigError(f"{path}: {name}={_listed(x)} holds {bad} non-finite values (NaN or inf); expected "
                              "finite numbers")
    bins = saved["bins"]
    if np.any(bins < 1):
        raise ConfigError(f"{path}: bins={_listed(bins)}: expected whole numbers >= 1, one per observation "
                          "dimension")
    states = math.prod(int(b) for b in bins)  # Python ints: a hostile count cannot overflow
    q = saved.get("q")
    if q is None or q.ndim != 4 or q.shape[2] != states:
        if q is None:
            raise ConfigError(f"{path}: no array 'q' (found {found})")
        raise ConfigError(f"{path}: q of shape {q.shape} has {q.shape[2] if q.ndim == 4 else '?'} states, but its "
                          f"bins={_listed(bins)} give {states}; expected q[n_envs, n_tables, n_states, n_actions] "
                          "with n_states the product of bins")
    for name, want in mine.items():
        x = saved[name]
        if not np.array_equal(x, want):
            i = int(np.flatnonzero(x != want)[0])
            raise ConfigError(f"{path}: the discretiser's {name}[{i}]={x[i]!s}, but the run's config.yaml builds "
                              f"{name}[{i}]={want[i]!s} ({kind} discretiser); the files are not of one run")
