"""``jaxrobo show``: top and side views of greedy quadcopter flights (path, start, goal, obstacles) to PNG.

Reads a training run directory (``config.yaml`` + ``qtables.npz``, as :mod:`jaxrobo.io.results` writes them) and
flies the greedy policy of one trained table; or, with ``--env ID``, flies an untrained (random) policy. A
``--agent ppo|sac`` run (``policy.npz`` + ``policy.json``, :mod:`jaxrobo.deep`) flies its saved deterministic
policy; for a task that does not fly (the continuous cart-pole) the figure shows each observation over the
episodes instead. ``--video PATH`` renders one episode of the same policy to a GIF/MP4 instead
(:func:`jaxrobo.pictures.render.record_episode`; Discrete and Box actions).
Obstacles and goals are task data (never physics bodies), so they are drawn from each episode's task state.
"""
from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np

from jaxrobo.io import rundir


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", nargs="?", help="training run directory (config.yaml, qtables.npz)")
    parser.add_argument("--env", dest="env_id", help="fly this env id with a random policy (no run needed)")
    parser.add_argument("--preset", default="default", help="agent preset when --env is given")
    parser.add_argument("--out", default="flights.png", help="PNG to write")
    parser.add_argument("--episodes", type=int, default=6, help="flights to draw")
    parser.add_argument("--table", type=int, default=0, help="which trained table (env index) to fly")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the flights")
    parser.add_argument("--video", metavar="PATH", default=None,
                        help="render one episode of the run's policy (a trained table, a saved ppo/sac policy, or "
                             "random with --env) to this .gif or .mp4 instead of drawing the figure; needs an "
                             "offscreen OpenGL (EGL or OSMesa). A ppo/sac run of any task renders, not only "
                             "quadcopter flights")


#: Task modules whose episodes ``fly`` can draw (they have a position and a goal): the quadcopter tasks.
FLYING_MODULES = ("envs.quadcopter.goto", "envs.quadcopter.goto_v2", "envs.quadcopter.live_show",
                  "envs.quadcopter.goto_twist")
#: Most flights one figure draws (each is a path and its obstacles in one picture).
MAX_EPISODES = 100


def check_flying(spec: Any, source: str) -> None:
    """ConfigError unless the run's env is a quadcopter task (``jaxrobo show`` draws flights)."""
    from jaxrobo.core.config import ConfigError

    module = type(spec.env).__module__
    if module not in FLYING_MODULES:
        raise ConfigError(f"{source}: env_id={spec.env_id!r} is not a quadcopter task; `jaxrobo show` draws flights "
                          f"of QuadcopterGoto-v1/-v2 or QuadcopterLiveShow-v0 (use `jaxrobo plot` for other runs)")


def _load_run(run_dir: str) -> tuple[Any, Any, np.ndarray | None]:
    """The run's RunSpec, config and tables, each checked (ConfigError naming the file and field)."""
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import load_config, load_tables
    from jaxrobo.training.run import resolve

    if not os.path.isdir(run_dir):
        raise ConfigError(f"run directory {run_dir!r} does not exist (or is not a directory)")
    try:
        cfg = load_config(run_dir)
    except FileNotFoundError as err:
        raise ConfigError(str(err)) from None
    where = os.path.join(run_dir, "config.yaml")
    if not isinstance(cfg.get("env_id"), str):
        raise ConfigError(f"{where}: env_id is missing; is it a jaxrobo run directory?")
    from jaxrobo.task.registry import find

    find(cfg["env_id"], where, may_import=False)  # a run directory never makes jaxrobo import code
    overrides = {f"env.{k}": v for k, v in (cfg.get("env_options") or {}).items()}
    overrides.update({f"env.{k}": v for k, v in (cfg.get("env_params") or {}).items()})
    overrides.update({f"agent.{k}": v for k, v in (cfg.get("agent_params") or {}).items()})
    overrides.update({f"agent.{k}": v for k, v in (cfg.get("train") or {}).items()})
    try:
        spec = resolve(cfg["env_id"], cfg.get("preset", "default"), overrides, check_memory=False)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None
    check_flying(spec, where)
    q = load_tables(run_dir)["q"]
    from jaxrobo.training.run import check_discretiser

    n_states, n_actions = check_discretiser(spec.env, spec.config), spec.env.num_actions
    if q.shape[2:] != (n_states, n_actions):
        raise ConfigError(f"{os.path.join(run_dir, 'qtables.npz')}: q has shape {q.shape}, but the run's config "
                          f"gives tables of {n_states} states x {n_actions} actions")
    return spec, cfg, q


def check_table(q: np.ndarray, table: int, source: str) -> None:
    """``--table`` must name one of the run's tables, and that table must hold finite values."""
    from jaxrobo.core.config import ConfigError

    if not 0 <= table < q.shape[0]:
        raise ConfigError(f"--table {table}: must be in 0..{q.shape[0] - 1} (the run has {q.shape[0]} tables)")
    if not np.all(np.isfinite(q[table])):
        bad = int(np.size(q[table]) - np.isfinite(q[table]).sum())
        raise ConfigError(f"{source}: table {table} has {bad} non-finite values of {np.size(q[table])}; "
                          "it cannot be flown")


def fly(spec: Any, q: np.ndarray | None, table: int, episodes: int, seed: int,
        policy: Any = None) -> dict[str, np.ndarray]:
    """Greedy flights of table ``q[table]`` (random flights when ``q`` is None; ``policy``, a
    :data:`jaxrobo.task.rollout.Policy`, flies that policy instead) as host arrays."""
    import jax

    from jaxrobo.task.rollout import greedy_policy, random_policy, rollout
    from jaxrobo.training.trainer import make_discretiser_for

    env = spec.env
    if policy is not None:
        pass
    elif q is None:
        policy = random_policy(env.num_actions)
    else:
        policy = greedy_policy(np.asarray(q[table]), make_discretiser_for(env, spec.config))
    position = lambda state: env.robot.read_sensors(state.pipeline_state)["pos"]  # noqa: E731
    out = jax.jit(lambda k: rollout(env, policy, k, episodes, observe=position))(jax.random.key(seed))
    task = out["first"].task
    res = {"pos": np.asarray(out["trace"]), "alive": np.asarray(out["alive"])}
    res["return"] = np.asarray(out["reward"]).sum(axis=1)
    if hasattr(task, "goal"):
        res["goal"] = np.asarray(task.goal)
        res["obs_kind"], res["obs_center"] = np.asarray(task.obstacles.kind), np.asarray(task.obstacles.center)
        res["obs_size"], res["obs_active"] = np.asarray(task.obstacles.size), np.asarray(task.obstacles.active)
        last = out["last"].task
        res["arrived"], res["crashed"] = np.asarray(last.arrived), np.asarray(last.crashed)
    else:  # the live show: a fixed goal from the parameters
        p = env.default_params
        res["goal"] = np.tile(np.array([p.goal_x, p.goal_y, p.goal_z], np.float32), (episodes, 1))
    return res


def draw(res: dict[str, np.ndarray], title: str, out: str, tolerance: float = 0.5,
         max_altitude: float | None = None) -> None:
    """Top view (x-y) and side view (distance along the path - z) of each flight, obstacles drawn to scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Rectangle

    n = res["pos"].shape[0]
    fig, (top, side) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.1, 1]})
    colors = plt.cm.tab10(np.arange(n) % 10)
    for i in range(n):
        alive = res["alive"][i]
        path = res["pos"][i][alive]
        goal = res["goal"][i]
        c = colors[i]
        outcome = ""
        if "arrived" in res:
            outcome = " arrived" if res["arrived"][i] else (" crashed" if res["crashed"][i] else " timeout")
        top.plot(path[:, 0], path[:, 1], "-", color=c, lw=1.8, label=f"flight {i}{outcome}")
        top.plot(path[0, 0], path[0, 1], "o", color=c, ms=6)
        top.plot(path[-1, 0], path[-1, 1], "x", color=c, ms=8)
        top.add_patch(Circle(goal[:2], tolerance, fill=False, ec=c, ls="--"))
        top.plot(goal[0], goal[1], "*", color=c, ms=14, mec="k")
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path[:, :2], axis=0), axis=1))])
        side.plot(along, path[:, 2], "-", color=c, lw=1.8)
        side.plot(along[-1], path[-1, 2], "x", color=c, ms=8)
        side.plot(along[-1], goal[2], "*", color=c, ms=10, mec="k")
        if "obs_kind" in res:
            for k, ctr, size, act in zip(res["obs_kind"][i], res["obs_center"][i], res["obs_size"][i],
                                         res["obs_active"][i]):
                if not act:
                    continue
                if k == 1:
                    top.add_patch(Circle(ctr[:2], size[0], color=c, alpha=0.25))
                else:
                    top.add_patch(Rectangle(ctr[:2] - size[:2], 2 * size[0], 2 * size[1], color=c, alpha=0.25))
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.set_title("top view: o start, x end, * goal (dashed: arrival radius), shaded: obstacles")
    top.grid(alpha=0.3)
    top.legend(fontsize=7, loc="best")
    side.axhline(0.0, color="saddlebrown", lw=2)
    if max_altitude is not None:
        side.axhline(max_altitude, color="r", ls=":", label="max altitude")
        side.legend(fontsize=8)
    side.set_xlabel("distance flown over the ground (m)")
    side.set_ylabel("altitude z (m)")
    side.set_title("side view")
    side.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    rundir.atomic_savefig(fig, out, dpi=110)
    plt.close(fig)


def check_args(args: argparse.Namespace) -> None:
    """The flags of ``jaxrobo show`` (ConfigError naming the flag and what it accepts)."""
    from jaxrobo.pictures.plots import check_image_path
    from jaxrobo.core.config import ConfigError
    from jaxrobo.core.struct import INT32_MAX

    if args.run_dir and args.env_id:
        raise ConfigError(f"give a RUN_DIR or --env ID, not both (got {args.run_dir!r} and --env {args.env_id})")
    if not args.run_dir and not args.env_id:
        raise ConfigError("give a RUN_DIR (greedy flights of a trained run) or --env ID (random flights)")
    if not 1 <= args.episodes <= MAX_EPISODES:
        raise ConfigError(f"--episodes {args.episodes}: must be an integer >= 1 and <= {MAX_EPISODES}")
    if not 0 <= args.seed <= INT32_MAX:
        raise ConfigError(f"--seed {args.seed}: must be an integer >= 0 and <= {INT32_MAX}")
    if args.table < 0:
        raise ConfigError(f"--table {args.table}: must be an integer >= 0")
    check_image_path(args.out)
    if args.video is not None:
        ext = os.path.splitext(args.video)[1].lower()
        if ext not in VIDEO_EXTENSIONS:
            raise ConfigError(f"--video {args.video!r}: expected a file ending in {', '.join(VIDEO_EXTENSIONS)}")
        if os.path.isdir(args.video):
            raise ConfigError(f"--video {args.video!r} is a directory; give a file name")


#: What ``--video`` writes (``.gif`` needs only imageio; the others imageio-ffmpeg).
VIDEO_EXTENSIONS = (".gif", ".mp4", ".mov", ".avi", ".mkv")


def video(spec: Any, path: str, seed: int, policy: Any = None, q: np.ndarray | None = None, table: int = 0) -> int:
    """Render one episode to ``path``: of ``policy`` (a :data:`jaxrobo.task.rollout.Policy` ``(key, obs) -> action``,
    a saved ppo/sac policy), of the greedy table ``q[table]``, or random; an exit code (1 with the reason where
    no offscreen OpenGL can be had)."""
    import sys

    from jaxrobo.pictures import render

    if policy is not None:
        host = render.jax_policy(policy, seed)
    elif q is not None:
        from jaxrobo.training.trainer import make_discretiser_for

        host = render.q_policy(np.asarray(q[table]), make_discretiser_for(spec.env, spec.config), seed)
    else:
        host = None
    try:
        info = render.record_episode(spec.env, path, host, seed=seed)
    except render.RenderUnavailable as err:
        print(f"jaxrobo show: --video: cannot render: {err}", file=sys.stderr)
        return 1
    print(f"wrote {path} ({info['frames']} frames: return {info['return']:.2f}, {info['length']} steps"
          f"{', terminated' if info['terminated'] else ''})")
    return 0


def _load_deep_run(run_dir: str, table: int) -> tuple[Any, Any]:
    """A ``--agent ppo|sac`` run's spec and its saved policy as a :data:`jaxrobo.task.rollout.Policy` of the env."""
    from jaxrobo import deep
    from jaxrobo.interop.brax_env import BraxEnv
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import load_config

    from jaxrobo.task.registry import find

    where = os.path.join(run_dir, "config.yaml")
    cfg = load_config(run_dir)
    find(cfg.get("env_id"), where, may_import=False)  # a run directory never makes jaxrobo import code
    spec = deep.spec_from_config(cfg, where)
    if table != 0:
        raise ConfigError(f"--table {table}: a {spec.agent} run has one policy (table 0)")
    loaded = deep.load_policy(run_dir)
    benv = BraxEnv(spec.env)
    sizes = (loaded.net["observation_size"], loaded.net["action_size"])
    if sizes != (benv.observation_size, benv.action_size):
        raise ConfigError(f"{os.path.join(run_dir, deep.POLICY_JSON)}: a policy of {sizes[0]} observations -> "
                          f"{sizes[1]} actions, but {spec.env_id} has {benv.observation_size} -> {benv.action_size}")
    return spec, deep.env_policy(benv, loaded.make_policy, loaded.params)


def trace(spec: Any, policy: Any, episodes: int, seed: int) -> dict[str, np.ndarray]:
    """Episodes of ``policy`` with every observation recorded (for a task that does not fly)."""
    import jax

    from jaxrobo.task.rollout import rollout

    out = jax.jit(lambda k: rollout(spec.env, policy, k, episodes, observe=lambda st: st.obs))(jax.random.key(seed))
    return {"obs": np.asarray(out["trace"]), "alive": np.asarray(out["alive"]), "return": np.asarray(out["return"]),
            "length": np.asarray(out["length"])}


def draw_traces(res: dict[str, np.ndarray], names: Any, title: str, out: str) -> None:
    """One panel per observation dimension, one line per episode, over the episode's steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_obs = res["obs"].shape[-1]
    fig, axes = plt.subplots(n_obs, 1, figsize=(9, 1.8 * n_obs + 1), sharex=True, squeeze=False)
    for i in range(res["obs"].shape[0]):
        alive = res["alive"][i]
        for d in range(n_obs):
            axes[d, 0].plot(np.flatnonzero(alive), res["obs"][i][alive, d], lw=1.2,
                            label=f"episode {i}: {int(res['length'][i])} steps" if d == 0 else None)
    for d in range(n_obs):
        axes[d, 0].set_ylabel(names[d] if names is not None and d < len(names) else f"obs[{d}]", fontsize=8)
        axes[d, 0].grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("step")
    fig.suptitle(title)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    rundir.atomic_savefig(fig, out, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    """Draw flights from a run directory (greedy) or an env id (random policy); returns a process exit code."""
    import sys

    from jaxrobo.core.config import ConfigError
    from jaxrobo.training.run import resolve

    from jaxrobo import deep

    policy = None
    try:
        check_args(args)
        if args.run_dir and deep.is_deep_run(args.run_dir):
            spec, policy = _load_deep_run(args.run_dir, args.table)
            q = None
            what = f"{spec.agent} policy, {args.run_dir}"
            if args.video is not None:
                return video(spec, args.video, args.seed, policy=policy)
            if type(spec.env).__module__ not in FLYING_MODULES:
                res = trace(spec, policy, args.episodes, args.seed)
                space = spec.env.observation_space()
                draw_traces(res, getattr(space, "names", None),
                            f"{spec.env_id}: {what} - mean return {res['return'].mean():.1f}, mean length "
                            f"{res['length'].mean():.1f}", args.out)
                print(f"wrote {args.out}")
                return 0
        elif args.run_dir:
            spec, cfg, q = _load_run(args.run_dir)
            check_table(q, args.table, os.path.join(args.run_dir, "qtables.npz"))
            what = f"greedy flights of table {args.table}, {args.run_dir}"
        else:
            spec, q = resolve(args.env_id, args.preset, check_memory=False), None
            check_flying(spec, f"--env {args.env_id}")
            what = "random policy (untrained)"
    except ConfigError as err:
        print(f"jaxrobo show: {err}", file=sys.stderr)
        return 2
    if args.video is not None:
        return video(spec, args.video, args.seed, q=q, table=args.table)
    res = fly(spec, q, args.table, args.episodes, args.seed, policy=policy)
    p = spec.env.default_params
    summary = ""
    if "arrived" in res:
        summary = f" - arrived {int(res['arrived'].sum())}/{len(res['arrived'])}"
    draw(res, f"{spec.env_id}: {what}{summary}", args.out, float(getattr(p, "goal_tolerance", 0.5)),
         float(getattr(p, "max_altitude", 0.0)) or None)
    print(f"wrote {args.out}")
    return 0
