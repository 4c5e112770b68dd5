"""The run directory of a deep run: kept at every evaluation point while it trains (:class:`LiveRun`: the checkpoint,
the latest and the best policy, ``episode_stats.csv``, TensorBoard scalars flushed, ``status.json``), and the
finished run (:func:`write_run`: ``config.yaml``, the policy, ``evaluations.csv``, ``episode_stats.csv``,
``training_metrics.csv``, ``summary.json``, the TensorBoard events of the run, ``rewards.png``), written into a
staging directory that :mod:`jaxrobo.io.rundir` publishes whole; :func:`eval_means` is the one definition of the
numbers that the progress line, ``episode_stats.csv`` and TensorBoard show; :func:`is_deep_run`."""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from jaxrobo.deep.config import is_deep
from jaxrobo.deep.policy import POLICIES, save_policy
from jaxrobo.deep.training import DeepResult, Point, best_index

#: ``evaluations.csv``: one row per evaluation episode.
EVAL_COLUMNS = ("evaluation", "env_steps", "episode", "return", "length", "terminated")
#: ``episode_stats.csv`` of a deep run: one row per evaluation (``episode`` is the evaluation's index, so
#: ``jaxrobo plot`` reads it as it reads a tabular run's; ``env_steps`` is the common x axis of both kinds).
STAT_COLUMNS = ("episode", "env_steps", "seconds", "return_mean", "return_std", "return_p10", "return_p50",
                "return_p90", "length_mean", "length_std", "length_p10", "length_p50", "length_p90")


def eval_means(e: dict[str, Any]) -> dict[str, float]:
    """An evaluation's numbers as every view shows them (progress line, ``episode_stats.csv``, TensorBoard):
    ``return_mean`` and ``length_mean`` over its episodes, ``success_rate`` (a task with success flags) and
    ``env_steps_per_second`` (env steps over the training wall time so far, evaluations excluded)."""
    out = {"return_mean": float(np.mean(e["return"].astype(np.float64))),
           "length_mean": float(np.mean(e["length"].astype(np.float64))),
           "env_steps_per_second": e["env_steps"] / max(float(e["seconds"]), 1e-9)}
    if "success" in e:
        out["success_rate"] = float(np.mean(e["success"]))
    return out


def _stats_rows(evaluations: list[dict[str, Any]]) -> tuple[tuple[str, ...], list[list[Any]]]:
    with_success = "success" in evaluations[0]
    cols = STAT_COLUMNS + (("success_rate",) if with_success else ())
    rows = []
    for i, e in enumerate(evaluations):
        r, n = e["return"].astype(np.float64), e["length"].astype(np.float64)
        means = eval_means(e)
        row: list[Any] = [i, e["env_steps"], f"{e['seconds']:.3f}"]
        for x, mean in ((r, means["return_mean"]), (n, means["length_mean"])):
            row += [f"{v:.6g}" for v in (mean, x.std(), *np.percentile(x, (10, 50, 90)))]
        if with_success:
            row.append(f"{means['success_rate']:.6g}")
        rows.append(row)
    return cols, rows


def _write_stats(out_dir: str, evaluations: list[dict[str, Any]]) -> None:
    import csv

    from jaxrobo.io import rundir

    cols, rows = _stats_rows(evaluations)

    def write(f):
        w = csv.writer(f)
        w.writerow(cols)
        w.writerows(rows)

    rundir.atomic_write(os.path.join(out_dir, "episode_stats.csv"), write, mode="w")


#: Where a run's TensorBoard events go.
TENSORBOARD = "tensorboard"


class LiveRun:
    """Keeps a deep run's work in its directory ``live`` at each evaluation point (:meth:`point`, the ``on_point`` of
    :func:`jaxrobo.deep.training.train`), in this order: the latest policy (``policy.npz`` + ``policy.json``, with the
    point's ``evaluation`` and ``env_steps``), the best one when this point is the best so far (``best/``), the
    checkpoint (:mod:`jaxrobo.deep.checkpoint`; what ``--resume`` trusts), then ``episode_stats.csv``, TensorBoard
    scalars (written and closed: readable while the run goes on) and ``status.json``. A stop, a crash or a kill at any
    moment leaves the last point's files whole."""

    def __init__(self, live: str, fingerprint: dict[str, Any], resume_cmd: str, saved: Any = None,
                 out: str | None = None):
        from jaxrobo.io import rundir

        self.live, self.fingerprint, self.resume_cmd = live, fingerprint, resume_cmd
        self.out = os.path.abspath(out if out is not None else live)
        self.checkpoint_path = os.path.join(live, rundir.CHECKPOINT)
        # A resumed run (``saved``: its checkpoint) drops the events a stopped session wrote after that checkpoint's
        # last point (all of them where it stopped before its first epoch: that run starts again).
        going_on = saved is not None and (saved.epochs_done > 0 or saved.chunks_done > 0)
        self._purge = None if saved is None else int(saved.evaluations[-1]["env_steps"]) + 1 if going_on else 0
        self._metrics_written = len(saved.training_metrics) if going_on else 0

    def _tensorboard(self, point: int) -> Any:
        """A writer of this point's events. tensorboardX's ``flush()`` does not wait for the events its writer
        thread has not taken yet, ``close()`` does: each point's events go to a file of their own (named by the
        point, so two in one second do not collide), closed at once, so a reader finds every point so far."""
        try:
            from jaxrobo.io.events import tensorboardx

            SummaryWriter = tensorboardx().SummaryWriter
        except ImportError:  # pragma: no cover - a dependency, but keep runs working without it
            return None
        purge, self._purge = self._purge, None
        return SummaryWriter(os.path.join(self.live, TENSORBOARD), purge_step=purge, filename_suffix=f".{point:05d}")

    def point(self, p: Point) -> None:
        from jaxrobo.io import rundir

        e, i = p.row, len(p.evaluations) - 1
        net = {**p.net, "evaluation": i, "env_steps": int(e["env_steps"])}
        save_policy(self.live, p.params, net)
        if best_index(p.evaluations, getattr(p.spec.env, "learning_target", None)) == i:
            os.makedirs(os.path.join(self.live, POLICIES["best"]), exist_ok=True)
            save_policy(os.path.join(self.live, POLICIES["best"]), p.params, net)
        self._checkpoint(p)
        _write_stats(self.live, p.evaluations)
        writer = self._tensorboard(i)
        if writer is not None:
            try:
                _scalars(writer, [e], p.training_metrics[self._metrics_written:])
            finally:
                writer.close()
            self._metrics_written = len(p.training_metrics)
        rundir.write_status(self.live, rundir.RUNNING, out=self.out, env_steps=int(e["env_steps"]),
                            total_steps=p.plan.total_steps, epochs_done=p.epochs_done, epochs=p.plan.epochs,
                            resume=self.resume_cmd)

    def _checkpoint(self, p: Point) -> None:
        from jaxrobo.deep import checkpoint

        checkpoint.save(self.checkpoint_path, self.fingerprint, p.epochs_done, p.states, p.evaluations,
                        p.training_metrics, p.train_seconds, p.chunks_done, p.partial_metrics)

    def chunk(self, p: Point) -> None:
        """Keep the trainer's state at the end of a host iteration between evaluation points (the ``on_chunk`` of
        :func:`jaxrobo.deep.training.train`): the checkpoint, then ``status.json``; the policies and the record
        stay those of the last point."""
        from jaxrobo.io import rundir

        self._checkpoint(p)
        rundir.write_status(self.live, rundir.RUNNING, out=self.out, env_steps=p.env_steps,
                            total_steps=p.plan.total_steps, epochs_done=p.epochs_done, epochs=p.plan.epochs,
                            resume=self.resume_cmd)



def write_run(out_dir: str, result: DeepResult, live: str | None = None,
              summary_extra: dict[str, Any] | None = None) -> str:
    """Everything a deep run produced, into ``out_dir`` (a staging directory: :mod:`jaxrobo.io.rundir` publishes
    it whole): ``config.yaml``, ``policy.npz`` + ``policy.json`` (the trained policy) and ``best/`` (the best
    evaluation's), ``evaluations.csv``, ``episode_stats.csv``, ``training_metrics.csv``, ``summary.json``,
    ``tensorboard/`` (the events :class:`LiveRun` wrote in ``live`` as the run went; written here from the result
    where there are none) and ``rewards.png``. ``summary_extra``: more keys for ``summary.json`` (the command's
    start-up seconds)."""
    import csv
    import shutil

    from jaxrobo.io.results import write_config, write_summary

    write_config(out_dir, result.spec.to_dict())
    last = len(result.evaluations) - 1
    save_policy(out_dir, result.params, {**result.net, "evaluation": last, "env_steps": result.env_steps})
    best_dir = None if live is None else os.path.join(live, POLICIES["best"])
    if best_dir is not None and os.path.isdir(best_dir):
        shutil.copytree(best_dir, os.path.join(out_dir, POLICIES["best"]))
    with_success = "success" in result.evaluations[0]
    with open(os.path.join(out_dir, "evaluations.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(EVAL_COLUMNS + (("success",) if with_success else ()))
        for i, e in enumerate(result.evaluations):
            for j in range(e["return"].shape[0]):
                row = [i, e["env_steps"], j, f"{e['return'][j]:.6g}", int(e["length"][j]), int(e["terminated"][j])]
                w.writerow(row + ([int(e["success"][j])] if with_success else []))
    _write_stats(out_dir, result.evaluations)
    if result.training_metrics:
        keys = sorted({k for m in result.training_metrics for k in m} - {"env_steps"})
        with open(os.path.join(out_dir, "training_metrics.csv"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["env_steps", *keys])
            for m in result.training_metrics:
                w.writerow([m["env_steps"], *(f"{m[k]:.6g}" if k in m else "" for k in keys)])
    write_summary(out_dir, {**result.summary(), **(summary_extra or {})})
    events = None if live is None else os.path.join(live, TENSORBOARD)
    if events is not None and os.path.isdir(events):
        shutil.copytree(events, os.path.join(out_dir, TENSORBOARD))
    else:
        _write_tensorboard(out_dir, result)
    from jaxrobo.pictures.plots import plot_runs

    plot_runs([out_dir], os.path.join(out_dir, "rewards.png"), labels=[f"{result.spec.env_id} · {result.spec.agent}"],
              window=1)
    return out_dir


def _scalars(writer: Any, evaluations: list[dict[str, Any]], training_metrics: list[dict[str, float]]) -> None:
    """TensorBoard scalars (x: env steps): each evaluation's :func:`eval_means` under ``eval/``, and Brax's
    training metrics under their own names."""
    for e in evaluations:
        step = int(e["env_steps"])
        for name, value in eval_means(e).items():
            writer.add_scalar(f"eval/{name}", value, step)
    for m in training_metrics:
        for k, v in m.items():
            if k != "env_steps" and np.isfinite(v):
                writer.add_scalar(k, v, int(m["env_steps"]))


def _write_tensorboard(out_dir: str, result: DeepResult) -> None:
    """All of a run's scalars at once (a run written without a :class:`LiveRun`)."""
    from jaxrobo.io.events import ScalarWriter

    try:
        writer = ScalarWriter(os.path.join(out_dir, TENSORBOARD))
    except ImportError:  # pragma: no cover - a dependency, but keep runs working without it
        return
    try:
        _scalars(writer, result.evaluations, result.training_metrics)
    finally:
        writer.close()


def is_deep_run(run_dir: str) -> bool:
    """A run directory written by a deep-RL run (its ``config.yaml`` names ``ppo`` or ``sac``)."""
    from jaxrobo.io.results import load_config

    try:
        return is_deep((load_config(run_dir).get("train") or {}).get("agent"))
    except (FileNotFoundError, OSError, ValueError):
        return False
