"""The cart-pole's learners side by side: docs/cartpole.md's "What it learns" commands, run as the page gives them.

The page's three ``jaxrobo train`` commands (Q-learning and Sarsa with the ``default`` preset, the ``seed`` preset;
16 envs, every table evaluated) each run as a fresh process (``python -m jaxrobo.cli train ...``) in a work folder
whose ``runs/`` holds the run directories under the page's names; then the page's ``jaxrobo plot`` command draws
their picture (``docs/cartpole_compare.png`` by default). Each row is one run's figures, read from its directory:

- ``best_100_window_mean_length``: ``summary.json``'s best 100-episode window of mean length (each env's best
  window, averaged over the envs; the run's printed "best 100-episode window"), recomputed from ``episodes.csv``;
- ``eval_mean_length``: the greedy evaluation, every table x ``eval_episodes`` episodes (``summary.json``, the mean
  of ``eval.csv``'s lengths);
- ``tables_ge_500``: the tables whose greedy mean length is at least 500 (the learning target), counted in
  ``eval.csv`` and checked against ``summary.json``'s ``eval_share_of_tables_over_500``;
- ``selected_table_fresh_mean_length``: the best table flown again on ``fresh_episodes`` fresh episodes;
- ``last_100_mean_length``: the mean length of every env's last 100 training episodes (``episodes.csv``);
- ``first_episode_window_ge_250`` / ``_500``: the first episode at which the mean length over the envs, averaged
  over the last 100 episodes (``episode_stats.csv``), reaches 250 / 500 steps (None: never): which learner rises
  earlier.

The script stops with an error where a run's files disagree with its summary.

    python benchmarks/learners_compare.py                  # the page's commands; writes the picture and the JSON
    python benchmarks/learners_compare.py --n-envs 2 --nepisodes 20 --eval-episodes 5 --png /tmp/c.png \\
        --out /tmp/learners_compare.json                   # shrunk (a smoke run; its commands say so)

Writes ``learners_compare.json`` under ``benchmarks/results/<device>/`` unless ``--out`` names a file.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
if HERE not in sys.path:
    sys.path.insert(0, HERE)

from _common import ROOT, git_commit, write_json  # noqa: E402

ENV_ID = "CartPoleStayUp-v0"
#: The page's runs: (run directory under ``runs/``, learner and preset flags, whether the whole budget is forced,
#: whether the page's picture draws it). The other two learners are run too; Double Q-learning once more with the
#: 16 envs' one shared table (its per-env tables learn too slowly on the cart-pole: the page says so from these).
RUNS = (("cpu_cartpole_qlearn", ["--agent", "qlearn"], True, True),
        ("cpu_cartpole_sarsa", ["--agent", "sarsa"], True, True),
        ("cpu_cartpole_seed", ["--preset", "seed"], False, True),
        ("cpu_cartpole_expected_sarsa", ["--agent", "expected_sarsa"], True, False),
        ("cpu_cartpole_double_q", ["--agent", "double_q"], True, False),
        ("cpu_cartpole_double_q_shared", ["--agent", "double_q", "--set", "shared_table=true"], True, False))

def _target():
    """The task's declared learning target (mean greedy episode length >= its threshold), read from its class."""
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    from envs.cartpole.stay_up import CartPoleStayUp

    return CartPoleStayUp.learning_target


TARGET = _target()
WINDOW = 100
RISE = (250, 500)


def commands(n_envs: int, nepisodes: int | None, eval_episodes: int | None) -> list[list[str]]:
    """The page's ``jaxrobo train`` commands (arguments after ``jaxrobo``), with ``n_envs`` envs and every table
    evaluated; ``nepisodes`` / ``eval_episodes`` add a ``--set`` (a shrunk run, not the page's)."""
    out = []
    for name, learner, whole, _ in RUNS:
        cmd = ["train", "--env", ENV_ID, *learner, "--n-envs", str(n_envs)]
        if whole:
            cmd += ["--set", "stop_at_target=false"]
        cmd += ["--set", f"eval_envs={n_envs}"]
        if nepisodes is not None:
            cmd += ["--set", f"nepisodes={nepisodes}"]
        if eval_episodes is not None:
            cmd += ["--set", f"eval_episodes={eval_episodes}"]
        out.append(cmd + ["--out", f"runs/{name}"])
    return out


def plot_command(png: str) -> list[str]:
    return ["plot", *(f"runs/{name}" for name, _, _, drawn in RUNS if drawn), "--out", png]


def _csv(path: str) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-6 * max(1.0, abs(a), abs(b))


def best_window(lengths: list[float], window: int = WINDOW) -> float:
    """The best ``window``-episode moving mean of one env's lengths (all of them where it has fewer)."""
    if len(lengths) <= window:
        return sum(lengths) / len(lengths)
    run = sum(lengths[:window])
    best = run
    for i in range(window, len(lengths)):
        run += lengths[i] - lengths[i - window]
        best = max(best, run)
    return best / window


def first_at(means: list[float], level: float, window: int = WINDOW) -> int | None:
    """The first episode at which the trailing ``window``-episode mean of ``means`` (only full windows, or the
    whole run where it is shorter) reaches ``level``; None if it never does."""
    window = min(window, len(means))
    run = sum(means[:window - 1])
    for i in range(window - 1, len(means)):
        run += means[i]
        if run / window >= level:
            return i
        run -= means[i - window + 1]
    return None


def figures(run_dir: str) -> dict[str, Any]:
    """One run's figures from its directory (see the module's docstring); raises where its files disagree."""
    with open(os.path.join(run_dir, "summary.json")) as f:
        s = json.load(f)
    episodes = _csv(os.path.join(run_dir, "episodes.csv"))
    per_env: dict[int, list[float]] = {}
    for e in episodes:
        per_env.setdefault(int(e["env"]), []).append(float(e["length"]))
    windows = [best_window(v) for v in per_env.values()]
    best = sum(windows) / len(windows)
    if not _close(best, s["best_100_window_mean_length"]):
        raise RuntimeError(f"{run_dir}: best window {best} from episodes.csv, {s['best_100_window_mean_length']} "
                           "in summary.json")
    last = [x for v in per_env.values() for x in v[-WINDOW:]]
    tables: dict[int, list[float]] = {}
    for e in _csv(os.path.join(run_dir, "eval.csv")):
        tables.setdefault(int(e["table"]), []).append(float(e["length"]))
    lengths = [x for v in tables.values() for x in v]
    eval_mean = sum(lengths) / len(lengths)
    if not _close(eval_mean, s["eval_mean_length"]):
        raise RuntimeError(f"{run_dir}: greedy mean length {eval_mean} from eval.csv, {s['eval_mean_length']} in "
                           "summary.json")
    share = s[f"eval_share_of_tables_{TARGET.name}"]
    at_target = sum(sum(v) / len(v) >= TARGET.threshold for v in tables.values())
    if not _close(at_target / len(tables), share):
        raise RuntimeError(f"{run_dir}: {at_target} of {len(tables)} tables >= {TARGET.threshold:g} in eval.csv, "
                           f"share {share} in summary.json")
    means = [float(r["length_mean"]) for r in _csv(os.path.join(run_dir, "episode_stats.csv"))]
    config = {}
    with open(os.path.join(run_dir, "config.yaml")) as f:
        for line in f:
            key, _, value = line.strip().partition(": ")
            if key in ("nepisodes", "eval_episodes", "seed", "stop_at_target", "shared_table"):
                config[key] = value
    row: dict[str, Any] = {
        "best_100_window_mean_length": round(s["best_100_window_mean_length"], 2),
        "eval_mean_length": round(s["eval_mean_length"], 2),
        "tables_ge_500": at_target,
        "tables_evaluated": len(tables),
        # None for one shared table: nothing is selected, so it is not flown again on fresh episodes
        "selected_table_fresh_mean_length": (round(s["selected_table_fresh_mean_length"], 2)
                                             if "selected_table_fresh_mean_length" in s else None),
        "last_100_mean_length": round(sum(last) / len(last), 2),
        **{f"first_episode_window_ge_{level}": first_at(means, level) for level in RISE},
    }
    row.update({"agent": s["agent"], "n_envs": s["n_envs"], "nepisodes": s["nepisodes"],
                "episodes_finished": s["episodes_finished"], "env_steps": s["env_steps"],
                "eval_episodes_per_table": len(lengths) // len(tables), "fresh_episodes": int(config["eval_episodes"]),
                "seed": int(config["seed"]), "stop_at_target": config["stop_at_target"] == "true",
                "shared_table": config.get("shared_table") == "true",
                "selected_table": s.get("selected_table"),
                "eval_best_table_mean_length": s.get("eval_best_table_mean_length"),
                "compile_seconds": s.get("compile_seconds"), "run_seconds": s.get("run_seconds")})
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n-envs", type=int, default=16, help="envs (independent learners) of each run, every table "
                                                          "evaluated (the page's: 16)")
    p.add_argument("--nepisodes", type=int, default=None, help="episodes per env (default: the presets' 1000)")
    p.add_argument("--eval-episodes", type=int, default=None, help="greedy episodes per table (default: the "
                                                                   "presets' 100)")
    p.add_argument("--png", default=os.path.join(ROOT, "docs", "cartpole_compare.png"),
                   help="the picture the plot command draws (default docs/cartpole_compare.png)")
    p.add_argument("--work", default=None, help="folder whose runs/ keeps the run directories (default: a "
                                                "temporary folder, removed)")
    p.add_argument("--out", default=None, help="the JSON file (default benchmarks/results/<device>/"
                                               "learners_compare.json)")
    args = p.parse_args(argv)
    for flag, value in (("--n-envs", args.n_envs), ("--nepisodes", args.nepisodes),
                        ("--eval-episodes", args.eval_episodes)):
        if value is not None and value < 1:
            p.error(f"{flag} {value}: expected an integer >= 1")
    import importlib.metadata

    code = git_commit("envs", "agents", "benchmarks/learners_compare.py")
    png = os.path.abspath(args.png)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(x for x in (ROOT, os.environ.get("PYTHONPATH")) if x)}
    shown = lambda cmd: " ".join(["jaxrobo", *cmd])  # noqa: E731
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="jaxrobo-learners-") as tmp:
        work = os.path.abspath(args.work) if args.work else tmp
        os.makedirs(os.path.join(work, "runs"), exist_ok=True)
        for (name, *_), cmd in zip(RUNS, commands(args.n_envs, args.nepisodes, args.eval_episodes)):
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "jaxrobo.cli", *cmd], cwd=work, env=env,
                                  capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                print(proc.stdout[-2000:], proc.stderr[-3000:], sep="\n", file=sys.stderr)
                raise SystemExit(f"{shown(cmd)}: exit code {proc.returncode}")
            row = {"run": name, **figures(os.path.join(work, "runs", name)), "wall_seconds": round(wall, 2),
                   "exit_code": proc.returncode, "command": shown(cmd)}
            print(json.dumps(row), flush=True)
            rows.append(row)
        plot = plot_command(png)
        proc = subprocess.run([sys.executable, "-m", "jaxrobo.cli", *plot], cwd=work, env=env, capture_output=True,
                              text=True)
        if proc.returncode != 0 or not os.path.isfile(png):
            raise SystemExit(f"{shown(plot)}: exit code {proc.returncode}\n{proc.stderr[-3000:]}")
    rel_png = os.path.relpath(png, ROOT) if png.startswith(ROOT + os.sep) else png
    plot[-1] = rel_png
    out = {"device": f"cpu ({os.cpu_count()} cores)" if os.environ.get("JAX_PLATFORMS") == "cpu" else None,
           "jax": importlib.metadata.version("jax"), "code": code,
           "command": " ".join(["python benchmarks/learners_compare.py", *(sys.argv[1:] if argv is None else argv)]),
           "note": "docs/cartpole.md's 'What it learns' commands, each a fresh process: " + "; ".join(
               r["command"] for r in rows) + f"; then {shown(plot)}. best_100_window_mean_length: the best "
           "100-episode window of mean length (each env's, averaged); eval_mean_length: greedy, every table x "
           "eval_episodes_per_table episodes; tables_ge_500: tables with a greedy mean length >= 500 (the target); "
           "selected_table_fresh_mean_length: the best table on fresh_episodes fresh episodes; "
           "first_episode_window_ge_N: first episode at which the mean length over the envs, averaged over the "
           "last 100 episodes, reaches N (- never)",
           "n_envs": args.n_envs, "png": rel_png, "rows": rows}
    if out["device"] is None:
        from _common import device_name

        out["device"] = device_name()
    path = write_json(out, args.out, "learners_compare.json")
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
