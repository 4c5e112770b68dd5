"""The run directory of a deep run (:func:`write_run`: ``config.yaml``, the policy, ``evaluations.csv``,
``episode_stats.csv``, ``training_metrics.csv``, ``summary.json``, TensorBoard scalars, ``rewards.png``), written
into a staging directory that :mod:`jaxrobo.io.rundir` publishes whole, and :func:`is_deep_run`."""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from jaxrobo.deep.config import is_deep
from jaxrobo.deep.policy import save_policy
from jaxrobo.deep.training import DeepResult

#: ``evaluations.csv``: one row per evaluation episode.
EVAL_COLUMNS = ("evaluation", "env_steps", "episode", "return", "length", "terminated")
#: ``episode_stats.csv`` of a deep run: one row per evaluation (``episode`` is the evaluation's index, so
#: ``jaxrobo plot`` reads it as it reads a tabular run's; ``env_steps`` is the common x axis of both kinds).
STAT_COLUMNS = ("episode", "env_steps", "seconds", "return_mean", "return_std", "return_p10", "return_p50",
                "return_p90", "length_mean", "length_std", "length_p10", "length_p50", "length_p90")


def _stats_rows(result: DeepResult) -> tuple[tuple[str, ...], list[list[Any]]]:
    with_success = "success" in result.evaluations[0]
    cols = STAT_COLUMNS + (("success_rate",) if with_success else ())
    rows = []
    for i, e in enumerate(result.evaluations):
        r, n = e["return"].astype(np.float64), e["length"].astype(np.float64)
        row: list[Any] = [i, e["env_steps"], f"{e['seconds']:.3f}"]
        for x in (r, n):
            row += [f"{v:.6g}" for v in (x.mean(), x.std(), *np.percentile(x, (10, 50, 90)))]
        if with_success:
            row.append(f"{float(np.mean(e['success'])):.6g}")
        rows.append(row)
    return cols, rows


def write_run(out_dir: str, result: DeepResult) -> str:
    """Everything a deep run produced, into ``out_dir`` (a staging directory: :mod:`jaxrobo.io.rundir` publishes
    it whole): ``config.yaml``, ``policy.npz`` + ``policy.json``, ``evaluations.csv``, ``episode_stats.csv``,
    ``training_metrics.csv``, ``summary.json``, ``tensorboard/`` and ``rewards.png``."""
    import csv

    from jaxrobo.io.results import write_config, write_summary

    write_config(out_dir, result.spec.to_dict())
    save_policy(out_dir, result.params, result.net)
    with_success = "success" in result.evaluations[0]
    with open(os.path.join(out_dir, "evaluations.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(EVAL_COLUMNS + (("success",) if with_success else ()))
        for i, e in enumerate(result.evaluations):
            for j in range(e["return"].shape[0]):
                row = [i, e["env_steps"], j, f"{e['return'][j]:.6g}", int(e["length"][j]), int(e["terminated"][j])]
                w.writerow(row + ([int(e["success"][j])] if with_success else []))
    cols, rows = _stats_rows(result)
    with open(os.path.join(out_dir, "episode_stats.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        w.writerows(rows)
    if result.training_metrics:
        keys = sorted({k for m in result.training_metrics for k in m} - {"env_steps"})
        with open(os.path.join(out_dir, "training_metrics.csv"), "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["env_steps", *keys])
            for m in result.training_metrics:
                w.writerow([m["env_steps"], *(f"{m[k]:.6g}" if k in m else "" for k in keys)])
    write_summary(out_dir, result.summary())
    _write_tensorboard(out_dir, result)
    from jaxrobo.pictures.plots import plot_runs

    plot_runs([out_dir], os.path.join(out_dir, "rewards.png"), labels=[f"{result.spec.env_id} · {result.spec.agent}"],
              window=1)
    return out_dir


def _write_tensorboard(out_dir: str, result: DeepResult) -> None:
    """Scalars at each evaluation (x: env steps): the evaluation's mean return, length (and success rate), and
    Brax's training metrics."""
    try:
        from tensorboardX import SummaryWriter
    except ImportError:  # pragma: no cover - a dependency, but keep runs working without it
        return
    writer = SummaryWriter(os.path.join(out_dir, "tensorboard"))
    try:
        for e in result.evaluations:
            step = int(e["env_steps"])
            writer.add_scalar("eval/return_mean", float(np.mean(e["return"])), step)
            writer.add_scalar("eval/length_mean", float(np.mean(e["length"])), step)
            if "success" in e:
                writer.add_scalar("eval/success_rate", float(np.mean(e["success"])), step)
        for m in result.training_metrics:
            for k, v in m.items():
                if k != "env_steps" and np.isfinite(v):
                    writer.add_scalar(k, v, int(m["env_steps"]))
    finally:
        writer.close()


def is_deep_run(run_dir: str) -> bool:
    """A run directory written by a deep-RL run (its ``config.yaml`` names ``ppo`` or ``sac``)."""
    from jaxrobo.io.results import load_config

    try:
        return is_deep((load_config(run_dir).get("train") or {}).get("agent"))
    except (FileNotFoundError, OSError, ValueError):
        return False
