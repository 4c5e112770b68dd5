"""``jaxrobo sweep``: the flags, their checks at the boundary, ``--resume``, and the run from flags to results.

The sweep-defining flags (:data:`SWEEP_FLAGS`) are saved with the sweep's state, so ``--resume DIR`` runs the same sweep
again (:func:`sweep_flags`). :func:`run` plans the sweep (:mod:`jaxrobo.training.sweep.planning`), runs it
(:mod:`jaxrobo.training.sweep.running`) under the signal handlers of :class:`jaxrobo.training.driver.StopOnSignal`, and
publishes ``sweep.csv``, ``summary.json`` and the heatmaps (:mod:`jaxrobo.training.sweep.output`) in one rename.

Public surface: :data:`SWEEP_FLAGS`, :func:`configure_parser`, :func:`sweep_flags`, :func:`points_from_args`,
:func:`run`, :func:`main`.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import sys
import time
from typing import Any, Mapping, Sequence

import jax
import numpy as np

from jaxrobo.training import budget, driver
from jaxrobo.core.config import ConfigError, merge_flags, parse_overrides
from jaxrobo.core.struct import INT32_MAX
from jaxrobo.training.sweep.output import _fmt, plot_sweep, write_csv
from jaxrobo.training.sweep.planning import _canonical, grid_points, parse_grid, parse_ranges, plan_sweep, random_points
from jaxrobo.training.sweep.running import METRICS, SweepInterrupted, run_plan
from jaxrobo.training.sweep.state import open_state, read_state

#: What ``jaxrobo sweep --help`` says the command does.
DESCRIPTION = "Parameter sweeps as one vmapped, jitted computation: ``jaxrobo sweep``."


#: The flags that define a sweep, with their defaults: saved with its state and read back by ``--resume``.
SWEEP_FLAGS: dict[str, Any] = {"env": "CartPoleStayUp-v0", "agent": None, "preset": "default", "grid": None,
                               "random": 0, "ranges": None, "seeds": 4, "seed": 0, "n_envs": None, "nepisodes": None,
                               "nsteps": None, "set": None, "eval_episodes": 10, "metric": "final_return",
                               "no_plots": False, "total_steps": None, "total_episodes": None}
_FLAG_NAMES = {"ranges": "--range", "n_envs": "--n-envs", "eval_episodes": "--eval-episodes",
               "no_plots": "--no-plots", "total_steps": "--total-steps", "total_episodes": "--total-episodes"}


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``jaxrobo sweep``. The sweep-defining flags parse to None when absent (defaults in
    :data:`SWEEP_FLAGS`), so ``--resume`` can tell a flag given again from one left out."""
    d = SWEEP_FLAGS
    parser.add_argument("--env", default=None, help=f"environment id (see `jaxrobo list`; default {d['env']})")
    parser.add_argument("--agent", default=None, help="qlearn | sarsa | expected_sarsa | double_q")
    parser.add_argument("--preset", default=None, help="parameter preset of the env's agent YAML (default default)")
    parser.add_argument("--grid", action="append", metavar="KEY=V1,V2,...",
                        help="values of one swept key (repeatable; the grid is their product)")
    parser.add_argument("--random", type=int, default=None, metavar="N", help="N random points from the --range's")
    parser.add_argument("--range", action="append", metavar="KEY=LOW:HIGH[:log]", dest="ranges",
                        help="sampling range of one key for --random (repeatable)")
    parser.add_argument("--seeds", type=int, default=None,
                        help=f"seeds per configuration (rows = configs × seeds; default {d['seeds']})")
    parser.add_argument("--seed", type=int, default=None, help="first seed; seeds are SEED .. SEED+N-1 (default 0)")
    parser.add_argument("--n-envs", type=int, default=None, help="environments (tables) per row")
    parser.add_argument("--nepisodes", type=int, default=None, help="episodes per environment")
    parser.add_argument("--nsteps", type=int, default=None, help="step cap per episode")
    parser.add_argument("--total-steps", type=int, default=None, metavar="N",
                        help="step budget of each row: N env steps, all its envs together (the batch stays full)")
    parser.add_argument("--total-episodes", type=int, default=None, metavar="N",
                        help="episode budget of each row: its envs step until the row has finished N episodes")
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", help="fixed override for every row")
    parser.add_argument("--eval-episodes", type=int, default=None,
                        help=f"greedy evaluation episodes of each row's first table (0: none; default "
                             f"{d['eval_episodes']})")
    parser.add_argument("--metric", default=None, choices=METRICS,
                        help=f"what ranks configurations (default {d['metric']})")
    parser.add_argument("--shard", choices=("auto", "on", "off"), default="auto",
                        help="split rows over all devices (auto: when there is more than one)")
    parser.add_argument("--out", default=None, help="output directory (default sweep_results/<env>_<time>); "
                        "must be new or empty unless --overwrite")
    parser.add_argument("--overwrite", action="store_true", help="replace the jaxrobo run or sweep in --out")
    parser.add_argument("--resume", default=None, metavar="DIR",
                        help="go on with the interrupted sweep in DIR: its saved settings, its unfinished groups")
    parser.add_argument("--no-plots", action="store_true", default=None, help="skip the heatmap PNGs")
    parser.add_argument("--no-progress", action="store_true", help="no line per training chunk inside a group")


def _flag(dest: str) -> str:
    return _FLAG_NAMES.get(dest, "--" + dest)


def _show(value: Any) -> str:
    if isinstance(value, bool):
        return "(given)" if value else "(not given)"
    return " ".join(map(str, value)) if isinstance(value, list) else str(value)


def sweep_flags(args: argparse.Namespace, check_out: bool = True) -> tuple[str, dict[str, Any], list[str]]:
    """The output directory, the sweep-defining flags and the command line of the sweep, checked at the boundary.

    A new sweep: ``--out`` must be new or empty (or a run, with ``--overwrite``); ``check_out=False`` skips that
    check (processes other than 0, which never write it). ``--resume DIR``: DIR must hold an interrupted sweep,
    whose saved flags are used (a flag given again must say the same) and whose ``status.json`` names the output
    directory (DIR itself, or the run an ``--overwrite`` sweep replaces). Raises :class:`ConfigError` naming the
    flag."""
    from jaxrobo.io import rundir
    from jaxrobo.task.registry import find

    given = {k: getattr(args, k, None) for k in SWEEP_FLAGS}
    if args.resume is None:
        env_id = given["env"] or SWEEP_FLAGS["env"]
        find(env_id, where=f"--env {env_id}")  # imports the module of a 'module:Id'; a missing one names --env
        out = args.out or os.path.join("sweep_results", f"{env_id.rpartition(':')[2]}_"
                                                        f"{time.strftime('%Y%m%d-%H%M%S')}")
        if check_out:
            out = rundir.check_out(out, overwrite=args.overwrite)
        flags = {k: SWEEP_FLAGS[k] if v is None else v for k, v in given.items()}
        return out, flags, list(sys.argv)
    live = args.resume
    if args.overwrite:
        raise ConfigError(f"--resume {live}: cannot be combined with --overwrite (one continues the sweep, the "
                          "other replaces it)")
    if args.out is not None:
        raise ConfigError(f"--out {args.out}: a resumed sweep finishes where it was going to; drop --out")
    live = rundir.check_out(live, resume=True, flag="--resume")
    extra = read_state(live).get("extra", {})
    saved = extra.get("flags") if isinstance(extra, dict) else None
    if not isinstance(saved, dict) or set(saved) != set(SWEEP_FLAGS):
        raise ConfigError(f"--resume {live}: its sweep state has no command-line flags to resume from")
    _check_saved_flags(live, saved)
    for k, v in given.items():
        if v is not None and _canonical(v) != saved[k]:
            raise ConfigError(f"--resume {live}: {_flag(k)} {_show(v)} differs from the saved sweep's "
                              f"{_flag(k)} {_show(saved[k])}; a resumed sweep keeps its settings (drop the flag)")
    # A 'module:Id' read back from the state imports its module only when --env gives it again (a file read back
    # never makes jaxrobo run code by itself).
    find(saved["env"], where=f"--resume {live}: env {saved['env']}", may_import=given["env"] == saved["env"])
    # Where the results go is derived from DIR itself, never from a path recorded in it: the sweep may have been
    # moved (a recorded path would write into, and replace, whatever is there now). DIR, or for the hidden
    # staging sibling of an --overwrite sweep (.NAME.<r>.partial), the run NAME beside it.
    out = rundir.run_name(live)
    return out, dict(saved), list(extra.get("argv") or [])


#: What each saved flag may be, as the parser gives it (None: the flag was not given).
_STR_FLAGS = ("env", "agent", "preset")
_LIST_FLAGS = ("grid", "ranges", "set")


def _check_saved_flags(live: str, saved: Mapping[str, Any]) -> None:
    """The flags read back from a sweep's state must be of the types the parser gives (a hand-edited
    ``sweep_state.json`` of ``"seeds": "4"`` or ``"metric": "best"`` would fail deep in the sweep, with a
    traceback): ConfigError naming the file and flag."""
    from jaxrobo.training.sweep.state import STATE_FILE

    for k, v in saved.items():
        if k in _STR_FLAGS:
            ok, want = v is None or isinstance(v, str), "a string"
        elif k in _LIST_FLAGS:
            ok, want = v is None or (isinstance(v, list) and all(isinstance(x, str) for x in v)), "a list of strings"
        elif k == "metric":
            ok, want = v in METRICS, f"one of {', '.join(METRICS)}"
        elif k == "no_plots":
            ok, want = isinstance(v, bool), "true or false"
        else:
            ok, want = v is None or (isinstance(v, int) and not isinstance(v, bool)), "an integer"
        if not ok:
            raise ConfigError(f"--resume {live}: {STATE_FILE}: saved flag {_flag(k)}={v!r}: expected {want}; "
                              "edited by hand?")


def _all_agree(ok: bool) -> bool:
    """Whether every process accepted the sweep: with several, all of them run it or none does (one alone
    would wait forever for the others)."""
    if jax.process_count() == 1:
        return ok
    from jax.experimental import multihost_utils

    return bool(np.all(multihost_utils.process_allgather(np.asarray(ok))))


def points_from_args(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The grid (product of --grid axes) times the --random sample (if any)."""
    axes = parse_grid(args.grid or [])
    ranges = parse_ranges(args.ranges or [])
    for key, values in list(axes.items()):  # "--grid alpha=0.05:0.9" with --random is a range
        if len(values) == 1 and isinstance(values[0], str) and ":" in values[0] and args.random:
            ranges.update(parse_ranges([f"{key}={values[0]}"]))
            del axes[key]
    if ranges and not args.random:
        raise ConfigError("--range needs --random N (how many points to draw)")
    if args.random and not ranges:
        raise ConfigError("--random N needs at least one --range KEY=LOW:HIGH")
    if args.random < 0:
        raise ConfigError(f"--random {args.random}: must be >= 0")
    seeds = getattr(args, "seeds", 1)  # points_from_args also serves callers that give no seeds
    if seeds < 1:
        raise ConfigError(f"--seeds {seeds}: must be >= 1")
    # Before a single point is built: a million-row sweep would fill the host's memory with Python objects.
    n_configs = int(np.prod([len(v) for v in axes.values()], dtype=object)) * max(args.random, 1)
    budget.check_sweep_rows(n_configs, seeds, where="--grid/--random x --seeds")
    grid = grid_points(axes)
    if not args.random:
        return grid
    sample = random_points(ranges, args.random, args.seed)
    return [{**g, **s} for g in grid for s in sample]


def check_swept_and_fixed(f: argparse.Namespace, overrides: Mapping[str, Any]) -> None:
    """A key both swept (``--grid``/``--range``) and fixed (``--set``, ``--n-envs``, ``--nepisodes``,
    ``--nsteps``) is refused: one of them would silently win. ``agent.``/``env.`` prefixes name the same key."""
    bare = lambda k: str(k).rpartition(".")[2]  # noqa: E731
    flags = {"n_envs": "--n-envs", "nepisodes": "--nepisodes", "nsteps": "--nsteps"}
    fixed = {bare(k): k for k in overrides}
    for item in (f.grid or []) + (f.ranges or []):
        key = item.partition("=")[0].strip()
        if bare(key) in fixed:
            k = fixed[bare(key)]
            given = flags.get(k, f"--set {k}={overrides[k]!r}")
            if k in flags:
                given = f"{given} {overrides[k]}"
            raise ConfigError(f"{key}: swept by --grid/--range and fixed by {given}; give it one way")


def run(args: argparse.Namespace, *, compiler_options: Mapping[str, Any] | None = None) -> int:
    """``jaxrobo sweep`` (see :func:`_run`); Ctrl-C before the sweep's own handlers are in place exits with 130
    and one line (nothing is half-written: the state and the results are written atomically).
    ``compiler_options``: XLA options for every group's plan (part of the sweep's saved settings)."""
    import contextlib

    try:
        with contextlib.ExitStack() as hold:  # the output directory's lock (process 0), released on any exit
            return _run(args, compiler_options, hold)
    except KeyboardInterrupt:
        print("jaxrobo sweep: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT


def _run(args: argparse.Namespace, compiler_options: Mapping[str, Any] | None = None, hold: Any = None) -> int:
    """``jaxrobo sweep``: train every row, write sweep.csv, summary.json and heatmaps, print the best.

    The sweep's state (``status.json``, ``sweep_state.json``, ``checkpoint.npz`` with the finished groups) lives
    in the output directory while it runs, or, with ``--overwrite``, in a hidden sibling, so that the old run
    stays whole until the new one replaces it. The results are written into a hidden sibling and replace the
    state (or the old run) in one rename. SIGINT / SIGTERM stop the sweep with exit status 130 / 143, the
    finished groups saved for ``--resume``."""
    from jaxrobo.io import rundir
    from jaxrobo.speed import sharding

    error = None
    try:
        sharding.initialize_distributed()  # a no-op unless JAXROBO_COORDINATOR & co. are set (docs/scaling.md)
        main_process = jax.process_index() == 0
        out, flags, argv = sweep_flags(args, check_out=main_process)
        # Where the state is: DIR, or the hidden sibling of an --overwrite sweep stopped beside the old one.
        live = None if args.resume is None else rundir.check_out(args.resume, resume=True, flag="--resume")
        f = argparse.Namespace(**flags)
        if f.seeds < 1:
            raise ConfigError(f"--seeds {f.seeds}: must be >= 1")
        if f.eval_episodes < 0:
            raise ConfigError(f"--eval-episodes {f.eval_episodes}: must be >= 0")
        if f.metric.startswith("eval_") and f.eval_episodes == 0:
            raise ConfigError(f"--metric {f.metric}: needs --eval-episodes > 0")
        points = points_from_args(f)
        overrides = merge_flags(parse_overrides(f.set or []), [("n_envs", "--n-envs", f.n_envs),
                                                                ("nepisodes", "--nepisodes", f.nepisodes),
                                                                ("nsteps", "--nsteps", f.nsteps),
                                                                ("total_steps", "--total-steps", f.total_steps),
                                                                ("total_episodes", "--total-episodes",
                                                                 f.total_episodes)])
        check_swept_and_fixed(f, overrides)
        if f.seed < 0 or f.seed + f.seeds - 1 > INT32_MAX:
            raise ConfigError(f"--seed {f.seed} --seeds {f.seeds}: the seeds run from --seed to --seed + --seeds - 1, "
                              f"which must lie in [0, {INT32_MAX}]")
        seeds = list(range(f.seed, f.seed + f.seeds))
        plan = plan_sweep(f.env, points, seeds, f.preset, f.agent, overrides, f.eval_episodes,
                          compiler_options=compiler_options)
        target = getattr(plan.groups[0].spec.env, "learning_target", None) if plan.groups else None
        if f.metric == "eval_success_rate" and (target is None or target.metric != "success_rate"):
            raise ConfigError(f"--metric eval_success_rate: {f.env} declares no success-rate learning target")
        if main_process and hold is not None:  # one writer per directory (a second is refused with the pid)
            hold.enter_context(rundir.claimed(live or out, overwrite=args.overwrite, resume=live is not None,
                                              flag="--out" if live is None else "--resume"))
        if args.resume is not None:
            open_state(live, plan)  # refuses a state of other settings or code before anything compiles
        mesh = None
        if args.shard == "on" or (args.shard == "auto" and jax.device_count() > 1):
            mesh = sharding.make_mesh()
    except sharding.JoinError as err:  # before any other process could be asked
        sharding.exit_after_join_error("jaxrobo sweep", err)
    except (ConfigError, ValueError) as err:
        error = str(err)
    if not _all_agree(error is None):
        print(f"jaxrobo sweep: {error or 'another process refused the sweep (see its output)'}", file=sys.stderr)
        return 2
    if main_process and live is None:
        # The state of a new sweep goes to --out itself (new or empty), so that a hard crash leaves it resumable;
        # with --overwrite (checked above) to a hidden sibling, so that the old run stays whole until the end.
        live = rundir.live_dir(out)
    resume_hint = (f"jaxrobo sweep --resume {shlex.quote(live)}" if live is not None
                   else "jaxrobo sweep --resume DIR (DIR as process 0 says)")
    if main_process:
        rundir.write_status(live, rundir.RUNNING, command="sweep", out=os.path.abspath(out), resume=resume_hint)
    print(f"{f.env}: {len(points)} configurations × {len(seeds)} seeds in {len(plan.groups)} groups"
          f"{f' over {mesh.devices.size} devices' if mesh is not None else ''} → {out}")
    if live is not None and os.path.abspath(live) != os.path.abspath(out):
        print(f"state in {live} until the sweep is done", file=sys.stderr)
    # Other processes read the state only when resuming (a new sweep's state directory is process 0's choice).
    state_dir = live
    owned = live if main_process else None  # the directory whose status this process writes
    with driver.StopOnSignal() as stop:
        # Processes stop together (a signal may reach only some of them): one more collective per chunk.
        should_stop = driver.agreed_stop(stop)
        saved_in = live or "process 0"
        try:
            result = run_plan(plan, mesh, log=print,
                              progress=None if getattr(args, "no_progress", False) else _chunk_line,
                              state_dir=state_dir, should_stop=should_stop,
                              state_extra={"flags": flags, "argv": argv})
        except KeyboardInterrupt:  # a second Ctrl-C: the chunk in flight is dropped at once
            rundir.interrupted(owned, out=out, resume=resume_hint, prog="jaxrobo sweep", command="sweep",
                               what=f"interrupted by SIGINT: the finished groups (and the last saved carry of the "
                                    f"group in progress, if any) are saved in {saved_in}")
            return 128 + signal.SIGINT
        except SweepInterrupted as err:
            name = stop.name or "a signal to another process"
            rundir.interrupted(owned, out=out, resume=resume_hint, prog="jaxrobo sweep", command="sweep",
                               finished_groups=err.done, groups=err.total,
                               **({"group_in_progress": err.partial[0] + 1, "group_chunks_done": err.partial[1],
                                   "group_chunks": err.partial[2]} if err.partial else {}),
                               what=f"interrupted by {name}: {err.where}, saved in {saved_in}")
            return 128 + (stop.signum or signal.SIGINT)
        except Exception as err:  # the finished groups are saved: say how to go on, then fail as before
            rundir.interrupted(owned, out=out, resume=resume_hint, prog="jaxrobo sweep", command="sweep",
                               error=f"{type(err).__name__}: {err}",
                               what=f"failed ({type(err).__name__}); the finished groups are saved in {saved_in}")
            raise
    if not main_process:
        return 0
    metric = f.metric
    best = result.best(metric)
    slots = sum(g.get("env_slots") or 0.0 for g in result.groups)
    summary = {"env_id": f.env, "agent": f.agent, "preset": f.preset, "swept": result.swept,
               "seeds": seeds, "n_rows": len(result.rows), "wall_seconds": result.wall_seconds,
               "env_steps": result.env_steps, "env_steps_per_second": result.env_steps / max(result.wall_seconds, 1e-9),
               "env_slots": slots, "useful_share": result.env_steps / slots if slots else None,
               "compile_seconds": sum(g["compile_seconds"] for g in result.groups),
               "run_seconds": sum(g["run_seconds"] for g in result.groups),
               "eval_seconds": sum(g.get("eval_seconds", 0.0) for g in result.groups),
               "groups": result.groups, "best": best, "argv": argv,
               # What "best" followed (the task's learning target), and what the window column is of.
               "best_100_window_of": result.ranking.words}
    plots: list[str] = []

    def write(staged: str) -> None:
        t = time.perf_counter()
        write_csv(result, os.path.join(staged, "sweep.csv"))
        plots.extend([] if f.no_plots else plot_sweep(result, staged, metric))
        summary["write_seconds"] = round(time.perf_counter() - t, 3)  # the table and plots; the summary is tiny
        with open(os.path.join(staged, "summary.json"), "w") as fh:
            json.dump(summary, fh, indent=2, default=str)
        rundir.write_status(staged, rundir.COMPLETE, command="sweep")

    rundir.publish_results(out, live, write)  # replaces the state (or the old run) in one step
    plots = [os.path.join(out, os.path.basename(p)) for p in plots]
    print(f"{len(result.rows)} rows, {result.env_steps:,} env steps in {result.wall_seconds:.1f} s "
          f"({summary['env_steps_per_second']:,.0f} steps/s incl. compile"
          + (f"; {summary['useful_share']:.1%} of the env slots useful)" if slots else ")"))
    print("best configuration: " + ", ".join(f"{k}={_fmt(best[k])}" for k in result.swept) +
          f"  ({metric} {best['mean']:.1f} ± {best['std']:.1f} over {best['seeds']} seeds, "
          f"{'higher' if best['higher'] else 'lower'} is better"
          + (f"; best_100_window is of the {result.ranking.words})" if metric == "best_100_window" else ")"))
    print(f"results: {os.path.join(out, 'sweep.csv')}" + (f"; plots: {', '.join(plots)}" if plots else ""))
    return 0


def _chunk_line(p: Any) -> None:
    """One line per chunk inside a group: the budget done (fewest of any row), useful share, speed and ETA."""
    eta = "?" if p.eta != p.eta else f"{p.eta:.0f} s"  # nothing of the budget done yet: no pace to go by
    print(f"    chunk {p.chunks_done}/{p.n_chunks}: {p.done:,}/{p.total:,} {p.unit} (fewest of any row), "
          f"last_return {p.last_return:.1f}, {p.useful_share:.0%} useful, "
          f"{p.steps_per_second:,.0f} steps/s, ETA {eta}", flush=True)


def main(argv: Sequence[str] | None = None, *, compiler_options: Mapping[str, Any] | None = None) -> int:
    from jaxrobo.core.cliargs import Parser

    parser = Parser(prog="jaxrobo sweep", description=DESCRIPTION)  # a usage error is one line
    configure_parser(parser)
    return run(parser.parse_args(argv), compiler_options=compiler_options)


if __name__ == "__main__":
    sys.exit(main())
