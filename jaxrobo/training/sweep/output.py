"""A sweep's results on disk: ``sweep.csv`` (one row per configuration and seed) and the heatmaps.

Public surface: :func:`write_csv`, :func:`plot_sweep`.
"""
from __future__ import annotations

import csv
import itertools
import os
from typing import Any

import numpy as np

from jaxrobo.io import rundir

from jaxrobo.training.sweep.running import SweepResult


def write_csv(result: SweepResult, path: str) -> None:
    keys = list(dict.fromkeys(k for r in result.rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(result.rows)


def plot_sweep(result: SweepResult, out_dir: str, metric: str = "final_return") -> list[str]:
    """Heatmaps of the mean ``metric`` over each pair of swept keys (scatter for sampled values); PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result.rows
    numeric = [k for k in result.swept if all(isinstance(r[k], (int, float)) and not isinstance(r[k], bool)
                                               for r in rows)]
    keys = [k for k in result.swept if len({r[k] for r in rows}) > 1]
    paths = []
    if len(keys) == 1:
        k = keys[0]
        xs = sorted({r[k] for r in rows}, key=_sort_key)
        means = [np.mean([r[metric] for r in rows if r[k] == x]) for x in xs]
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.scatter([str(r[k]) if k not in numeric else r[k] for r in rows], [r[metric] for r in rows], s=10,
                   alpha=0.4, label="one seed")
        ax.plot([str(x) if k not in numeric else x for x in xs], means, "o-", color="C1", label="mean over seeds")
        ax.set_xlabel(k)
        ax.set_ylabel(metric)
        ax.legend()
        paths.append(_save(fig, out_dir, f"sweep_{k}.png"))
    for a, b in itertools.combinations(keys, 2):
        xa = sorted({r[a] for r in rows}, key=_sort_key)
        xb = sorted({r[b] for r in rows}, key=_sort_key)
        fig, ax = plt.subplots(figsize=(1.2 + 0.8 * max(len(xa), 3), 1.2 + 0.6 * max(len(xb), 3)))
        pairs = {(r[a], r[b]) for r in rows}
        if len(pairs) == len(xa) * len(xb) <= 400:  # every combination present: a grid
            grid = np.full((len(xb), len(xa)), np.nan)
            for i, vb in enumerate(xb):
                for j, va in enumerate(xa):
                    vals = [r[metric] for r in rows if r[a] == va and r[b] == vb]
                    if vals:
                        grid[i, j] = np.mean(vals)
            im = ax.imshow(grid, origin="lower", aspect="auto", cmap="viridis")
            ax.set_xticks(range(len(xa)), [_fmt(v) for v in xa], rotation=45)
            ax.set_yticks(range(len(xb)), [_fmt(v) for v in xb])
            if grid.size <= 100:
                for i in range(len(xb)):
                    for j in range(len(xa)):
                        if np.isfinite(grid[i, j]):
                            ax.text(j, i, f"{grid[i, j]:.0f}", ha="center", va="center", color="w", fontsize=8)
        else:  # sampled values: one dot per row
            im = ax.scatter([r[a] for r in rows], [r[b] for r in rows], c=[r[metric] for r in rows], cmap="viridis")
        fig.colorbar(im, ax=ax, label=f"{metric} (mean over seeds)")
        ax.set_xlabel(a)
        ax.set_ylabel(b)
        ax.set_title(f"{result.env_id}: {metric}", fontsize=9)
        paths.append(_save(fig, out_dir, f"heatmap_{a}_{b}.png"))
    return paths


def _sort_key(v: Any) -> tuple:
    return (0, v, "") if isinstance(v, (int, float)) else (1, 0, str(v))


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _save(fig: Any, out_dir: str, name: str) -> str:
    import matplotlib.pyplot as plt

    path = os.path.join(out_dir, name)
    fig.tight_layout()
    rundir.atomic_savefig(fig, path, dpi=110)
    plt.close(fig)
    return path
