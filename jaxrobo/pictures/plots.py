"""``jaxrobo plot``: reward and length per episode, mean and 10-90 % band over envs, several runs overlaid.

The seed's ``plot_results`` drew the reward per episode of one run; comparing Q-learning with Sarsa "under the
exact same conditions" (seed exercise 2.2) means overlaying runs trained with the same seeds.

A deep-RL run (``--agent ppo|sac``) records evaluations, not training episodes: its ``episode_stats.csv`` has one
row per evaluation and an ``env_steps`` column. Runs of both kinds share one x axis, the env steps of training
(all envs together): a tabular run's are the cumulated mean episode length times its ``n_envs``
(:func:`env_steps_axis`). ``x="auto"`` uses env steps as soon as one run is a deep run, else episodes.
"""
from __future__ import annotations

import os
import time
from typing import Sequence

import numpy as np

from jaxrobo.io import rundir

from jaxrobo.core.config import ConfigError
from jaxrobo.io.results import load_config, load_stats


#: Image formats the PNG-writing commands accept (matplotlib picks the format from the extension).
IMAGE_EXTENSIONS = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def check_image_path(path: str, flag: str = "--out") -> None:
    """ConfigError unless ``path`` names an image file matplotlib writes, in a directory that is not a file."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in IMAGE_EXTENSIONS:
        raise ConfigError(f"{flag} {path!r}: expected an image file ending in {', '.join(IMAGE_EXTENSIONS)}")
    if os.path.isdir(path):
        raise ConfigError(f"{flag} {path!r} is a directory; give a file name")
    parent = os.path.dirname(os.path.abspath(path))
    while parent and not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if parent and not os.path.isdir(parent):
        raise ConfigError(f"{flag} {path!r}: {parent!r} is a file, not a directory")


def run_labels(run_dirs: Sequence[str]) -> list[str]:
    """A distinct legend label per run: its directory's name, with as many parent folders as it takes to tell
    apart runs whose names are the same (``a/q`` and ``b/q``)."""
    parts = [os.path.normpath(os.path.abspath(d)).split(os.sep) for d in run_dirs]
    labels = []
    for i, p in enumerate(parts):
        depth = 1
        while depth < len(p) and any(q[-depth:] == p[-depth:] for j, q in enumerate(parts) if j != i):
            depth += 1
        labels.append("/".join(p[-depth:]))
    return labels


#: The x axes ``plot_runs`` draws on.
X_AXES = ("auto", "episode", "env_steps")


def env_steps_axis(run_dir: str, stats: dict[str, np.ndarray]) -> np.ndarray:
    """Env steps of training (all envs) at each row of a run's stats: the ``env_steps`` column of a deep run;
    for a tabular run, the cumulated mean episode length times ``n_envs`` (every env runs its episodes side by
    side, so after episode ``i`` the envs have stepped about ``n_envs * sum(mean length up to i)`` times)."""
    if "env_steps" in stats:
        return np.asarray(stats["env_steps"], np.float64)
    cfg = load_config(run_dir)
    n_envs = (cfg.get("train") or {}).get("n_envs")
    if not isinstance(n_envs, int) or isinstance(n_envs, bool) or n_envs < 1:
        raise ValueError(f"{run_dir}: config.yaml has no train.n_envs (an integer >= 1) for the env-steps axis")
    length = np.asarray(stats["length_mean"], np.float64)
    return np.cumsum(np.where(np.isfinite(length), length, 0.0)) * n_envs  # a NaN row adds no steps


def smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average (window 1 = unchanged), the same length as ``x``, over the finite values only:
    a NaN or inf in a CSV (an episode of diverged physics, an episode no row of an ``episodes.csv`` holds) is a gap
    in the curve, never the end of it (a running sum would carry it to every later point); a window with no finite
    value is NaN (a gap)."""
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x)
    if window <= 1 or x.size == 0:
        return np.where(ok, x, np.nan)
    total = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    count = np.concatenate([[0], np.cumsum(ok)])
    i = np.arange(x.size)
    lo = np.maximum(0, i + 1 - window)
    n = count[i + 1] - count[lo]
    return np.where(n > 0, (total[i + 1] - total[lo]) / np.maximum(n, 1), np.nan)


def plot_runs(run_dirs: Sequence[str], out_png: str, labels: Sequence[str] | None = None, window: int = 10,
              title: str | None = None, x: str = "auto") -> str:
    """Draw reward and length per episode (or per evaluation, for a deep run) of each run into one PNG, against
    ``x``: ``"episode"``, ``"env_steps"`` or ``"auto"`` (env steps when one run is a deep run); returns its path.
    A deep run's rows are evaluations: they are never smoothed."""
    from matplotlib.figure import Figure

    if not run_dirs:
        raise ValueError("plot needs at least one run directory")
    labels = list(labels) if labels else run_labels(run_dirs)
    if len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    if not (isinstance(window, int) and window >= 1):
        raise ValueError(f"window={window!r}: must be an integer >= 1 (episodes averaged)")
    if x not in X_AXES:
        raise ValueError(f"x={x!r}: allowed values are {', '.join(X_AXES)}")
    all_stats = [load_stats(d) for d in run_dirs]  # every run read (and checked) before anything is drawn
    if x == "auto":
        x = "env_steps" if any("env_steps" in s for s in all_stats) else "episode"
    xs = [env_steps_axis(d, s) if x == "env_steps" else s["episode"] for d, s in zip(run_dirs, all_stats)]
    fig = Figure(figsize=(9, 7))  # no pyplot: a notebook's backend is left as it is
    ax_r, ax_l = fig.subplots(2, 1, sharex=True)
    for s, label, ep in zip(all_stats, labels, xs):
        w = 1 if "env_steps" in s else window
        for ax, name in ((ax_r, "return"), (ax_l, "length")):
            mean = smooth(s[f"{name}_mean"], w)
            (line,) = ax.plot(ep, mean, label=label, lw=1.6, marker="o" if "env_steps" in s else None, ms=3)
            ax.fill_between(ep, smooth(s[f"{name}_p10"], w), smooth(s[f"{name}_p90"], w),
                            color=line.get_color(), alpha=0.18, lw=0)
    ax_r.set_ylabel("reward per episode")
    ax_l.set_ylabel("episode length (steps)")
    ax_l.set_xlabel("env steps of training (all envs)" if x == "env_steps" else "episode")
    ax_r.legend(loc="best", fontsize=8)
    ax_r.set_title(title or f"mean over envs, band 10-90 %, moving average {window}")
    for ax in (ax_r, ax_l):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out_png)), exist_ok=True)
    rundir.atomic_savefig(fig, out_png, dpi=110)
    return out_png


def plot_scalars(run_dirs: Sequence[str], out_png: str, labels: Sequence[str] | None = None) -> str:
    """The runs' live TensorBoard scalars (``RUN/tensorboard``, as a running ``jaxrobo train`` flushes them every
    chunk or evaluation) in one PNG, a panel per tag and a line per run, against the step TensorBoard shows:
    TensorBoard's scalar page without a browser, readable mid-run. Returns the path."""
    from matplotlib.figure import Figure

    from jaxrobo.io.results import read_scalars

    labels = list(labels) if labels else run_labels(run_dirs)
    if len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    runs = [read_scalars(os.path.join(d, "tensorboard")) for d in run_dirs]
    tags = sorted({t for r in runs for t in r})
    if not tags:
        raise ValueError(f"{', '.join(run_dirs)}: no TensorBoard scalars written yet (the first come after the "
                         "first chunk or evaluation)")
    cols = min(3, len(tags))
    rows = -(-len(tags) // cols)
    fig = Figure(figsize=(4.2 * cols, 3.0 * rows))
    axes = np.atleast_1d(fig.subplots(rows, cols)).reshape(-1)
    for ax, tag in zip(axes, tags):
        for r, label in zip(runs, labels):
            if tag in r:
                steps, values = zip(*r[tag])
                ax.plot(steps, values, marker="o", ms=2.5, lw=1.3, label=label)
        ax.set_title(tag, fontsize=9)
        ax.set_xlabel("step", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes[len(tags):]:
        ax.set_visible(False)
    if len(run_dirs) > 1:
        axes[0].legend(fontsize=7)
    points = sum(len(v) for r in runs for v in r.values())
    fig.suptitle(f"TensorBoard scalars, {points} points read at {time.strftime('%H:%M:%S')}", fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out_png)), exist_ok=True)
    rundir.atomic_savefig(fig, out_png, dpi=110)
    return out_png


def robustness_figure(rows: Sequence[dict], out_png: str, title: str) -> None:
    """``jaxrobo eval``'s figure: one panel per shifted quantity, the metric (mean over tables, band from the worst
    to the best table) against the quantity's value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["shift"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        sel = sorted((r for r in rows if r["shift"] == name), key=lambda r: r["value"])
        x = np.array([r["value"] for r in sel])
        ax.plot(x, [r["mean"] for r in sel], "o-", color="C0", label="mean over tables")
        if any(r["tables"] > 1 for r in sel):
            ax.fill_between(x, [r["worst"] for r in sel], [r["best"] for r in sel], color="C0", alpha=0.2,
                            label="worst-best table")
        ax.set_xlabel(name)
        ax.set_ylabel(sel[0]["metric"])
        if sel[0]["metric"] == "success_rate":
            ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    rundir.atomic_savefig(fig, out_png, dpi=110)  # a stop while writing keeps the earlier figure whole
    plt.close(fig)
