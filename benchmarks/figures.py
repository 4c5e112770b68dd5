"""The throughput figures, a pure function of the results JSON that ``throughput.py`` writes.

    python benchmarks/figures.py benchmarks/results/h100/throughput.json            # next to the JSON
    python benchmarks/throughput.py --replot benchmarks/results/h100/throughput.json  # the same

* ``throughput.png``, the headline: at the largest batch, each jaxrobo env with learning in the loop beside
  each peer (its own largest batch), one panel per family, log scale, every bar labelled with its value;
  published figures (a peer's own, on its own hardware) hatched, labelled "published, other machine" and
  explained in the legend, so a CPU bar is never read as beaten on this machine by a GPU figure.
* ``throughput_<family>.png``, one scaling plot per family (rate against ``n_envs``), one colour and one marker
  per series, never more series than distinct colours; published series dotted with hollow markers, labelled
  the same way.

Cart-pole bars and curves are env steps per second (every cart-pole row here controls at 0.02-0.04 s); the
quadcopter ones are physics steps per second, the unit crazyflow and L2F publish.
"""
from __future__ import annotations

import json
import os
import sys
from typing import Any

#: family -> (row key, axis label); the family of a row is ``family(row)``
FAMILY_MEASURE = {"cart-pole": ("steps_per_s", "env steps per second"),
                  "quadcopter": ("physics_steps_per_s", "physics steps per second")}
FAMILY_FILE = {"cart-pole": "cartpole", "quadcopter": "quadcopter"}
PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22",
           "#7f7f7f", "#393b79", "#ad494a", "#637939", "#e7ba52", "#7b4173", "#3182bd", "#31a354", "#756bb1",
           "#fd8d3c", "#636363")  # 20 distinct colours: no two series of one plot share one
MARKERS = "osD^v<>phP*X8dH+x1234"
MAX_SERIES = 12  # per scaling plot: a legend one reads at a glance
#: jaxrobo series a scaling plot shows first
MAIN_MODES = ("env", "qlearn")
MAIN_BACKENDS = ("mjx", "analytic", "-")


#: The family (the task a user would compare) of each peer suite and of jaxrobo env ids by prefix: ratios compare
#: rows of one family only. An id of no family gets no peer ratio.
PEER_FAMILY = {"gymnax": "cart-pole", "brax": "cart-pole", "playground": "cart-pole", "gymnasium": "cart-pole",
               "gymnasium-sync": "cart-pole", "gymnasium-vec": "cart-pole", "seed-loop": "cart-pole",
               "crazyflow": "quadcopter", "l2f": "quadcopter"}
ENV_FAMILY = (("CartPole", "cart-pole"), ("Quadcopter", "quadcopter"))
def family(row: dict[str, Any]) -> str | None:
    if not row["suite"].startswith("jaxrobo"):  # jaxrobo-cli: the user's commands, end to end
        return PEER_FAMILY.get(row["suite"])
    return next((fam for prefix, fam in ENV_FAMILY if row["env"].startswith(prefix)), None)



def _rate(x: float) -> str:
    for unit, div in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= div:
            return f"{x / div:.3g} {unit}"
    return f"{x:.3g}"


def _n(n: int | None) -> str:
    if n is None:  # a published figure without its batch size
        return ""
    for unit, div in (("M", 1 << 20), ("k", 1 << 10)):
        if n >= div and n % div == 0:
            return f"n={n // div}{unit}"
    return f"n={n}"


def _label(r: dict[str, Any]) -> str:
    backend = "" if r["backend"] in ("-", "numpy") else f" [{r['backend']}]"
    return f"{r['suite']}: {r['env']}{backend}"


def published_label(r: dict[str, Any]) -> str:
    """The tag of a published figure: measured elsewhere, on the hardware its authors name (one wording for the
    bars, the curves and the legend)."""
    return f"(published, other machine: {r.get('hardware', '?')})"


#: The legend entry of the hatched bars: what they are, and that no ratio uses them.
PUBLISHED_NOTE = "published, other machine: the peer's own figure on its hardware, not measured here"


def _usable(r: dict[str, Any], key: str) -> bool:
    return r.get("status") in ("ok", "published") and bool(r.get(key))


def headline_bars(rows: list[dict[str, Any]], fam: str) -> list[dict[str, Any]]:
    """The headline panel of ``fam``: jaxrobo rows with a learner at the largest batch any of them ran (the first
    learner of each env and backend, by row order), then each peer suite's row at its largest batch (the fastest
    there); published rows as they are. Each bar: label, value, n_envs, published."""
    key = FAMILY_MEASURE[fam][0]
    rows = [r for r in rows if family(r) == fam and _usable(r, key)]
    learning = [r for r in rows if r["suite"] == "jaxrobo" and r["mode"] != "env" and r["status"] == "ok"]
    bars = []
    if learning:
        top = max(r["n_envs"] for r in learning)
        seen = set()
        for r in learning:
            ident = (r["env"], r["backend"])
            if r["n_envs"] == top and ident not in seen and r["suite"] != "seed-loop":
                seen.add(ident)
                bars.append({"label": f"{_label(r)} + {r['mode']}", "value": r[key], "n_envs": top,
                             "published": False})
    # The user's own commands, end to end (compile included): each command and budget at its largest batch.
    cli = [r for r in rows if r["suite"] == "jaxrobo-cli" and r["status"] == "ok"]
    for mode in dict.fromkeys(r["mode"] for r in cli):
        group = [r for r in cli if r["mode"] == mode]
        top = max(r["n_envs"] for r in group)
        for r in (r for r in group if r["n_envs"] == top):
            command, budget = mode.split("-")
            backend = "" if r["backend"] == "default" else f" [{r['backend']}]"
            bars.append({"label": f"jaxrobo {command} {r['env']}{backend} ({budget} budget), end to end",
                         "value": r[key], "n_envs": top, "published": False})
    peers: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if not r["suite"].startswith("jaxrobo"):
            peers.setdefault((r["suite"], r["status"]), []).append(r)
    for (suite, status), group in peers.items():
        if status == "published":
            for r in group:
                bars.append({"label": f"{_label(r)} {published_label(r)}", "value": r[key],
                             "n_envs": r.get("n_envs"), "published": True})
            continue
        top = max(r["n_envs"] for r in group)
        best = max((r for r in group if r["n_envs"] == top), key=lambda r: r[key])
        mode = "" if best["mode"] == "env" else f" + {best['mode']}"
        bars.append({"label": f"{_label(best)}{mode}", "value": best[key], "n_envs": top, "published": False})
    return bars


def headline(rows: list[dict[str, Any]], path: str, device: str) -> bool:
    """Write the headline bar chart; False (nothing written) when no family has a bar."""
    import matplotlib.pyplot as plt

    fig = headline_figure(rows, device)
    if fig is None:
        return False
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def headline_figure(rows: list[dict[str, Any]], device: str) -> Any:
    """The headline bar chart as a figure (None when no family has a bar): a panel with a published bar gets a
    legend telling the measured bars (this device) from the hatched published ones (another machine)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    panels = [(fam, headline_bars(rows, fam)) for fam in FAMILY_MEASURE]
    panels = [(fam, bars) for fam, bars in panels if bars]
    if not panels:
        return None
    # A panel with published bars carries a two-line legend above it: room for it.
    heights = [max(2.0, 0.42 * len(bars) + 1.2) + 0.4 * any(b["published"] for b in bars) for _, bars in panels]
    fig, axes = plt.subplots(len(panels), 1, figsize=(11, sum(heights)), squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    for ax, (fam, bars) in zip(axes[:, 0], panels):
        ys = range(len(bars))
        colours = [PALETTE[i % len(PALETTE)] for i in range(len(bars))]
        for y, b, c in zip(ys, bars, colours):
            if b["published"]:  # hatched, in its own colour: a figure not measured here
                ax.barh([y], [b["value"]], color="white", edgecolor=c, hatch="///", linewidth=1.0)
            else:
                ax.barh([y], [b["value"]], color=c, edgecolor="black", linewidth=0.4)
            ax.text(b["value"] * 1.08, y, f"{_rate(b['value'])}  {_n(b['n_envs'])}", va="center", fontsize=8)
        ax.set_yticks(list(ys))
        ax.set_yticklabels([b["label"] for b in bars], fontsize=8)
        ax.invert_yaxis()
        ax.set_xscale("log")
        lo = min(b["value"] for b in bars)
        hi = max(b["value"] for b in bars)
        ax.set_xlim(lo / 3, hi * 20)  # room for the labels right of the longest bar
        ax.set_xlabel(FAMILY_MEASURE[fam][1] + " (log)")
        published = any(b["published"] for b in bars)
        ax.set_title(f"{fam}: largest batch, jaxrobo with learning vs peers", fontsize=10, loc="left",
                     pad=30 if published else 6)  # above the legend, when there is one
        ax.grid(True, axis="x", which="major", alpha=0.3)
        if published:
            ax.legend(handles=[Patch(facecolor="#999999", edgecolor="black", label=f"measured on {device}"),
                               Patch(facecolor="white", edgecolor="#555555", hatch="///", label=PUBLISHED_NOTE)],
                      fontsize=7, loc="lower right", bbox_to_anchor=(1.0, 1.0), frameon=False)  # above the bars
    fig.suptitle(f"throughput on {device}", fontsize=11)
    fig.tight_layout()
    return fig


def scaling_series(rows: list[dict[str, Any]], fam: str) -> dict[str, list[tuple[int, float]]]:
    """``label -> [(n_envs, rate)]`` of ``fam``: every peer, and the jaxrobo series that show scaling (measured at
    several sizes, when any is), env-only and the first learner on the main backends first, up to
    ``MAX_SERIES`` in all. The rest stay in the table and the headline."""
    key = FAMILY_MEASURE[fam][0]
    series: dict[str, list[tuple[int, float]]] = {}
    rank: dict[str, tuple[bool, bool]] = {}
    for r in rows:
        if family(r) != fam or not _usable(r, key) or r.get("n_envs") is None:
            continue
        name = _label(r) + ("" if r["mode"] == "env" and r["suite"] != "jaxrobo" else f" {r['mode']}")
        if r["status"] == "published":
            name += f" {published_label(r)}"
        series.setdefault(name, []).append((r["n_envs"], r[key]))
        if r["suite"] == "jaxrobo":
            rank[name] = (r["mode"] not in MAIN_MODES, r["backend"] not in MAIN_BACKENDS)
    ours = [k for k in series if k in rank]
    peers = [k for k in series if k not in rank]
    if any(len(series[k]) > 1 for k in ours):
        ours = [k for k in ours if len(series[k]) > 1]
    ours = sorted(ours, key=lambda k: rank[k])[:max(0, MAX_SERIES - len(peers))]
    keep = [k for k in series if k in ours or k in peers][:MAX_SERIES]
    return {k: sorted(series[k]) for k in keep}


def scaling(rows: list[dict[str, Any]], fam: str, path: str, device: str) -> bool:
    """Write ``fam``'s scaling plot; False (nothing written) when it has no row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import NullFormatter

    series = scaling_series(rows, fam)
    if not series:
        return False
    fig, ax = plt.subplots(figsize=(10, 6))
    for i, (name, pts) in enumerate(series.items()):
        published = "(published" in name
        style = "-" if name.startswith("jaxrobo") else ":" if published else "--"
        ax.plot([p[0] for p in pts], [p[1] for p in pts], style, marker=MARKERS[i % len(MARKERS)],
                color=PALETTE[i], label=name, markersize=6, linewidth=1.6,
                fillstyle="none" if published else "full")  # hollow: a figure not measured here
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())  # a narrow span of sizes would label every minor tick
    ax.set_xlabel("n_envs (parallel environments)")
    ax.set_ylabel(FAMILY_MEASURE[fam][1])
    ax.set_title(f"{fam} on {device}\nsolid: jaxrobo, dashed: peers\ndotted, hollow: published, other machine",
                 fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def write_figures(data: dict[str, Any], out_dir: str) -> list[str]:
    """Every figure of one results JSON (``{"meta": ..., "rows": [...]}``) into ``out_dir``; the paths written."""
    rows, device = data["rows"], (data.get("meta") or {}).get("device", "?")
    os.makedirs(out_dir, exist_ok=True)
    written = []
    path = os.path.join(out_dir, "throughput.png")
    if headline(rows, path, device):
        written.append(path)
    for fam in FAMILY_MEASURE:
        path = os.path.join(out_dir, f"throughput_{FAMILY_FILE[fam]}.png")
        if scaling(rows, fam, path, device):
            written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("json", help="a throughput.json")
    p.add_argument("--out", default=None, help="output folder (default: the JSON's folder)")
    args = p.parse_args(argv)
    with open(args.json) as f:
        data = json.load(f)
    for path in write_figures(data, args.out or os.path.dirname(os.path.abspath(args.json))):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
