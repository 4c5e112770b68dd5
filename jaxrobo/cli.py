"""The ``jaxrobo`` command: ``train``, ``plot``, ``list``, and (when their modules are present) ``show``, ``sweep``.

Examples::

    jaxrobo train --env CartPoleStayUp-v0 --agent qlearn --n-envs 256 --set alpha=0.3 --out runs/q
    jaxrobo train --env CartPoleStayUp-v0 --agent sarsa --n-envs 256 --out runs/s
    jaxrobo plot runs/q runs/s --out runs/q_vs_sarsa.png
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from typing import Sequence

# Subcommands whose module provides configure_parser(parser) and run(args) -> int.
PLUGINS = {"show": ("jaxrobo.flights", "draw greedy flights of a trained quadcopter (top and side views)"),
           "sweep": ("jaxrobo.sweep", "parameter sweep as one vmapped computation")}


def _train(args: argparse.Namespace) -> int:
    from jaxrobo.config import ConfigError, parse_overrides
    from jaxrobo.results import save_run
    from jaxrobo.run import resolve
    from jaxrobo.train import Trainer, train

    try:
        overrides = parse_overrides(args.set or [])
        for key, flag in (("n_envs", args.n_envs), ("seed", args.seed), ("nepisodes", args.nepisodes)):
            if flag is not None:
                overrides[key] = flag
        spec = resolve(args.env, args.preset, overrides, agent=args.agent)
    except ConfigError as err:
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2
    out = args.out or os.path.join("training_results",
                                   f"{spec.env_id}_{spec.config.agent}_{time.strftime('%Y%m%d-%H%M%S')}")
    cfg = spec.config
    print(f"{spec.env_id} · {cfg.agent} ({spec.preset}) · {cfg.n_envs} envs × {cfg.nepisodes} episodes "
          f"≤ {cfg.nsteps} steps → {out}")
    bar = None
    if not args.no_progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.nepisodes, unit="ep", desc="training", dynamic_ncols=True)

    def progress(done: int, total: int, last_return: float) -> None:
        if bar is not None:
            bar.update(done - bar.n)
            bar.set_postfix(mean_reward=f"{last_return:.1f}")

    result = train(spec.env, cfg, spec.agent_params, progress=progress)
    if bar is not None:
        bar.close()
    save_run(out, result, spec.to_dict(), Trainer(spec.env, cfg).disc)
    s = result.summary()
    print(f"compiled in {s['compile_seconds']:.1f} s; {s['env_steps']:,} env steps in {s['run_seconds']:.1f} s "
          f"({s['env_steps_per_second']:,.0f} steps/s)")
    print(f"highest reward {s['highest_reward_max']:.0f} · overall mean length {s['overall_mean_length']:.1f} · "
          f"best 100 mean {s['best_100_mean_length']:.1f}")
    if "eval_mean_length" in s:
        print(f"greedy evaluation: mean length {s['eval_mean_length']:.1f}, mean return {s['eval_mean_return']:.1f} "
              f"over {result.eval_lengths.shape[0]} tables × {result.eval_lengths.shape[1]} episodes")
    if "selected_table" in s:
        print(f"best table ({s['selected_table']}) on fresh episodes: mean length "
              f"{s['selected_table_fresh_mean_length']:.1f}, mean return {s['selected_table_fresh_mean_return']:.1f}")
    if s["physics_nan_episodes"]:
        print(f"warning: {s['physics_nan_episodes']} episodes ended on non-finite physics", file=sys.stderr)
    print(f"results in {out}")
    return 0


def _plot(args: argparse.Namespace) -> int:
    from jaxrobo.plots import plot_runs

    for d in args.runs:
        if not os.path.isdir(d):
            print(f"jaxrobo plot: {d!r} is not a directory", file=sys.stderr)
            return 2
    out = args.out or os.path.join(args.runs[0], "rewards.png")
    try:
        plot_runs(args.runs, out, labels=args.labels, window=args.window)
    except (FileNotFoundError, ValueError) as err:
        print(f"jaxrobo plot: {err}", file=sys.stderr)
        return 2
    print(out)
    return 0


def _list(args: argparse.Namespace) -> int:
    import agents
    import jaxrobo
    from jaxrobo.run import agent_presets

    print("environments:")
    for env_id in jaxrobo.registered():
        spec = jaxrobo.spec(env_id)
        presets = ", ".join(agent_presets(env_id)) or "-"
        print(f"  {env_id:28s} max {spec.max_episode_steps:5d} steps  presets: {presets:14s} {spec.description}")
    print("agents: " + ", ".join(agents.LEARNERS))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxrobo", description="Train tabular agents on MJX robots, fast.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a tabular agent on many envs at once")
    p.add_argument("--env", default="CartPoleStayUp-v0", help="environment id (see `jaxrobo list`)")
    p.add_argument("--agent", default=None, help="qlearn | sarsa | expected_sarsa | double_q")
    p.add_argument("--preset", default="default", help="parameter preset of the env's agent YAML: default | seed")
    p.add_argument("--n-envs", type=int, default=None, help="environments (independent learners) run at once")
    p.add_argument("--nepisodes", type=int, default=None, help="episodes per environment")
    p.add_argument("--seed", type=int, default=None, help="random seed")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a parameter (repeatable)")
    p.add_argument("--out", default=None, help="run directory (default training_results/<env>_<agent>_<time>)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)

    p = sub.add_parser("plot", help="reward and length per episode of one or more runs, to PNG")
    p.add_argument("runs", nargs="+", help="run directories written by `jaxrobo train`")
    p.add_argument("--out", default=None, help="PNG path (default <first run>/rewards.png)")
    p.add_argument("--labels", nargs="*", default=None, help="legend labels, one per run")
    p.add_argument("--window", type=int, default=10, help="moving-average window in episodes")
    p.set_defaults(func=_plot)

    p = sub.add_parser("list", help="registered environments, presets and agents")
    p.set_defaults(func=_list)

    for name, (module, help_text) in PLUGINS.items():
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        p = sub.add_parser(name, help=help_text)
        mod.configure_parser(p)
        p.set_defaults(func=mod.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from jaxrobo.sim import quiet_imports

    with quiet_imports():
        import mujoco.mjx  # noqa: F401  (import once, silently: MJX prints warp import noise)
    try:
        from jaxrobo.cache import enable_compilation_cache

        enable_compilation_cache()
    except ImportError:
        pass
    args = build_parser().parse_args(argv)
    from jaxrobo.config import ConfigError

    try:
        return int(args.func(args) or 0)
    except ConfigError as err:  # a subcommand that does not catch it itself (show), e.g. JAX 64-bit mode is on
        print(f"jaxrobo {args.command}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
