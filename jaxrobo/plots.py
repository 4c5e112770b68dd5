"""``jaxrobo plot``: reward and length per episode, mean and 10-90 % band over envs, several runs overlaid.

The seed's ``plot_results`` drew the reward per episode of one run; comparing Q-learning with Sarsa "under the
exact same conditions" (seed exercise 2.2) means overlaying runs trained with the same seeds.
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from jaxrobo.results import load_config, load_stats


def run_label(run_dir: str) -> str:
    """``env · agent (preset)`` from a run's config, else the directory name."""
    try:
        cfg = load_config(run_dir)
        train = cfg.get("train", {})
        return f"{cfg.get('env_id', '?')} · {train.get('agent', '?')} ({cfg.get('preset', '?')})"
    except (FileNotFoundError, OSError, ValueError):  # a label only: a broken config.yaml is not fatal here
        return os.path.basename(os.path.normpath(run_dir))


def smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average (window 1 = unchanged), the same length as ``x``."""
    if window <= 1 or x.size == 0:
        return x
    c = np.cumsum(np.insert(np.asarray(x, np.float64), 0, 0.0))
    out = np.empty(x.size)
    for i in range(x.size):
        lo = max(0, i + 1 - window)
        out[i] = (c[i + 1] - c[lo]) / (i + 1 - lo)
    return out


def plot_runs(run_dirs: Sequence[str], out_png: str, labels: Sequence[str] | None = None, window: int = 10,
              title: str | None = None) -> str:
    """Draw reward and length per episode of each run into one PNG; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not run_dirs:
        raise ValueError("plot needs at least one run directory")
    labels = list(labels) if labels else [run_label(d) for d in run_dirs]
    if len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    if not (isinstance(window, int) and window >= 1):
        raise ValueError(f"window={window!r}: must be an integer >= 1 (episodes averaged)")
    all_stats = [load_stats(d) for d in run_dirs]  # every run read (and checked) before anything is drawn
    fig, (ax_r, ax_l) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for s, label in zip(all_stats, labels):
        ep = s["episode"]
        for ax, name in ((ax_r, "return"), (ax_l, "length")):
            mean = smooth(s[f"{name}_mean"], window)
            (line,) = ax.plot(ep, mean, label=label, lw=1.6)
            ax.fill_between(ep, smooth(s[f"{name}_p10"], window), smooth(s[f"{name}_p90"], window),
                            color=line.get_color(), alpha=0.18, lw=0)
    ax_r.set_ylabel("reward per episode")
    ax_l.set_ylabel("episode length (steps)")
    ax_l.set_xlabel("episode")
    ax_r.legend(loc="best", fontsize=8)
    ax_r.set_title(title or f"mean over envs, band 10-90 %, moving average {window}")
    for ax in (ax_r, ax_l):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out_png)), exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png
