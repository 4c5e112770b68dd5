"""``jaxrobo show``: what a policy does, for every task and learner, to a PNG (and a GIF/MP4 with ``--video``).

The policy comes from a training run directory: a tabular run's greedy table (``qtables.npz``, acting through the
run's own discretiser, rebuilt from its ``config.yaml``), or a ``--agent ppo|sac`` run's saved deterministic
policy (``policy.npz`` + ``policy.json``, :func:`jaxrobo.deep.load_policy`); with ``--env ID`` instead, a random
policy. A quadcopter task is drawn as flights (top and side views: path, start, goal, obstacles; obstacles and
goals are task data, never physics bodies, so they are drawn from each episode's task state). Any other task
(the cart-poles, the arm, a user's module task) is drawn as frames of the first episode (MuJoCo's offscreen
renderer, where an OpenGL library loads; otherwise the figure says why in one line), the return and length of
each episode, and every observation and action over the steps. ``--video PATH`` renders one episode of the same
policy to a GIF/MP4 instead (:func:`jaxrobo.pictures.render.record_episode`; Discrete and Box actions).
Figures are drawn on a :class:`matplotlib.figure.Figure` without pyplot, so a notebook's backend is left alone.
"""
from __future__ import annotations

import argparse
import os
from typing import Any

import numpy as np

from jaxrobo.io import rundir


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", nargs="?", help="training run directory (tabular or ppo/sac)")
    parser.add_argument("--env", dest="env_id", help="show this env id with a random policy (no run needed)")
    parser.add_argument("--preset", default=None, help="agent preset when --env is given (default: default)")
    parser.add_argument("--out", default=None,
                        help="image to write (default: RUN_DIR/show.png, or runs/show/ENV.png with --env)")
    parser.add_argument("--episodes", type=int, default=6, help="episodes to run and draw")
    parser.add_argument("--table", type=int, default=None,
                        help="which trained table (env index) to show; default the run's selected best table "
                             "(summary.json), else 0")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the episodes")
    parser.add_argument("--policy", default=None, choices=("latest", "best"),
                        help="a ppo/sac run's policy: latest (the default: the trained one; a stopped run's last "
                             "evaluation point's) or best (its best evaluation's)")
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


def flies(spec: Any) -> bool:
    """Whether ``jaxrobo show`` draws the run's episodes as flights (a quadcopter task: a position and a goal)."""
    return type(spec.env).__module__ in FLYING_MODULES


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
        spec = resolve(cfg["env_id"], cfg.get("preset", "default"), overrides, check_memory=False,
                       source="")  # an unknown key: named after the file, not as a --set
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None
    saved = load_tables(run_dir)
    from jaxrobo.io.results import check_saved_discretiser
    from jaxrobo.training.run import check_tables
    from jaxrobo.training.trainer import make_discretiser_for

    path = os.path.join(run_dir, "qtables.npz")
    check_tables(saved["q"], spec.env, spec.config, path)
    check_saved_discretiser(saved, make_discretiser_for(spec.env, spec.config), path)  # the one it acts through
    return spec, cfg, saved["q"]


def check_table(q: np.ndarray, table: int, source: str) -> None:
    """``--table`` must name one of the run's tables, and that table must hold finite values."""
    from jaxrobo.core.config import ConfigError

    if not 0 <= table < q.shape[0]:
        raise ConfigError(f"--table {table}: must be in 0..{q.shape[0] - 1} (the run has {q.shape[0]} tables)")
    if not np.all(np.isfinite(q[table])):
        bad = int(np.size(q[table]) - np.isfinite(q[table]).sum())
        raise ConfigError(f"{source}: table {table} has {bad} non-finite values of {np.size(q[table])}; "
                          "it cannot be flown")


def _table_policy(spec: Any, q: np.ndarray | None, table: int) -> Any:
    """Greedy in ``q[table]`` through the run's own discretiser (rebuilt from its config), or random when ``q`` is
    None: a :data:`jaxrobo.task.rollout.Policy`."""
    from jaxrobo.task.rollout import greedy_policy, random_policy
    from jaxrobo.training.trainer import make_discretiser_for

    if q is None:
        return random_policy(spec.env.num_actions)
    return greedy_policy(np.asarray(q[table]), make_discretiser_for(spec.env, spec.config))


def fly(spec: Any, q: np.ndarray | None, table: int, episodes: int, seed: int,
        policy: Any = None) -> dict[str, np.ndarray]:
    """Greedy flights of table ``q[table]`` (random flights when ``q`` is None; ``policy``, a
    :data:`jaxrobo.task.rollout.Policy`, flies that policy instead) as host arrays."""
    import jax

    from jaxrobo.task.rollout import rollout

    env = spec.env
    if policy is None:
        policy = _table_policy(spec, q, table)
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
    from matplotlib.patches import Circle, Rectangle

    n = res["pos"].shape[0]
    fig = _figure(figsize=(13, 5.5))
    top, side = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.1, 1]})
    colors = _colors(n)
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
        # Distance over the ground from the start, for the path and the goal alike: a flight that ends short of
        # its goal ends short of its star.
        along = np.linalg.norm(path[:, :2] - path[0, :2], axis=1)
        side.plot(along, path[:, 2], "-", color=c, lw=1.8)
        side.plot(0.0, path[0, 2], "o", color=c, ms=6)
        side.plot(along[-1], path[-1, 2], "x", color=c, ms=8)
        side.plot(np.linalg.norm(goal[:2] - path[0, :2]), goal[2], "*", color=c, ms=10, mec="k")
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
    side.set_xlabel("distance over the ground from the start (m)")
    side.set_ylabel("altitude z (m)")
    side.set_title("side view: o start, x end, * goal")
    side.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    rundir.atomic_savefig(fig, out, dpi=110)


def default_out(run_dir: str | None, env_id: str | None) -> str:
    """Where the figure goes without ``--out``: into the run directory, or the git-ignored ``runs/show/``."""
    if run_dir:
        return os.path.join(run_dir, "show.png")
    return os.path.join("runs", "show", "".join(c if c.isalnum() or c in "-_." else "_" for c in env_id) + ".png")


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
    if args.table is not None and args.table < 0:
        raise ConfigError(f"--table {args.table}: must be an integer >= 0")
    # Flags that would be silently ignored are refused, naming what they apply to.
    if args.env_id and args.table is not None:
        raise ConfigError(f"--table {args.table}: --env flies a random policy, which has no tables; drop --table")
    if args.env_id and args.policy is not None:
        raise ConfigError(f"--policy {args.policy}: --env flies a random policy; --policy chooses a ppo/sac run's "
                          "saved policy")
    if args.run_dir and args.preset is not None:
        raise ConfigError(f"--preset {args.preset}: a run directory flies with its own config.yaml; --preset "
                          "applies to --env only")
    if args.video is not None and args.out is not None:
        raise ConfigError(f"--out {args.out!r} with --video: --video writes the episode instead of the figure; "
                          "give one of them")
    if args.out is None:
        args.out = default_out(args.run_dir, args.env_id)
    check_image_path(args.out)
    if args.video is not None:
        ext = os.path.splitext(args.video)[1].lower()
        if ext not in VIDEO_EXTENSIONS:
            raise ConfigError(f"--video {args.video!r}: expected a file ending in {', '.join(VIDEO_EXTENSIONS)}")
        if os.path.isdir(args.video):
            raise ConfigError(f"--video {args.video!r} is a directory; give a file name")
        rundir.check_writable(args.video, "--video", directory=False)  # before the episode is rendered


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


def _load_deep_run(run_dir: str, table: int, which: str = "latest") -> tuple[Any, Any]:
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
    loaded = deep.load_policy(run_dir, which)
    benv = BraxEnv(spec.env)
    sizes = (loaded.net["observation_size"], loaded.net["action_size"])
    if sizes != (benv.observation_size, benv.action_size):
        raise ConfigError(f"{os.path.join(run_dir, deep.POLICY_JSON)}: a policy of {sizes[0]} observations -> "
                          f"{sizes[1]} actions, but {spec.env_id} has {benv.observation_size} -> {benv.action_size}")
    return spec, deep.env_policy(benv, loaded.make_policy, loaded.params)


#: Frames of the first episode drawn above the plots of a task that does not fly (when OpenGL renders).
FRAMES = 5


def episodes(spec: Any, policy: Any, n: int, seed: int) -> dict[str, Any]:
    """``n`` episodes of ``policy`` (a :data:`jaxrobo.task.rollout.Policy`) with every state recorded: ``obs``
    ``[n, T+1, n_obs]``, ``action`` ``[n, T]``, ``alive`` ``[n, T+1]``, per-episode ``return``/``length``/
    ``terminated`` (and ``arrived`` for a goal task) as host arrays, and ``states`` (the whole
    :class:`jaxrobo.task.env.EnvState` trace as host arrays, to render frames from)."""
    import jax

    from jaxrobo.task.rollout import outcomes, rollout

    out = jax.device_get(jax.jit(lambda k: rollout(spec.env, policy, k, n, observe=lambda st: st))(
        jax.random.key(seed)))
    res = {k: np.asarray(v) for k, v in jax.device_get(outcomes(out)).items()}
    res.update(obs=np.asarray(out["trace"].obs), action=np.asarray(out["action"]), alive=np.asarray(out["alive"]),
               states=out["trace"])
    return res


def render_frames(spec: Any, res: dict[str, Any], episode: int = 0, count: int = FRAMES,
                  width: int = 320, height: int = 240) -> tuple[list[tuple[int, np.ndarray]], str | None]:
    """``count`` frames ``(step, image)`` spread over episode ``episode`` of :func:`episodes`, and None; or no
    frames and the one-line reason where this machine cannot render (no offscreen OpenGL)."""
    import jax

    from jaxrobo.pictures import render

    reason = render.gl_unavailable_reason()
    if reason is not None:
        return [], reason
    length = int(res["length"][episode])
    steps = sorted({int(round(t)) for t in np.linspace(0, length, count)})
    frames = []
    try:
        with render.Renderer(spec.env, width, height) as r:
            for t in steps:
                state = jax.tree.map(lambda x: x[episode, t], res["states"])
                frames.append((t, r.render(state)))
    except (render.RenderUnavailable, ValueError) as err:
        return [], " ".join(str(err).split())
    return frames, None


def summary_line(res: dict[str, Any]) -> str:
    """Mean return and length of the episodes (and arrivals for a goal task), for titles and the terminal."""
    line = f"mean return {res['return'].mean():.2f}, mean length {res['length'].mean():.1f} steps"
    if "arrived" in res:
        line += f", arrived {int(res['arrived'].sum())}/{len(res['arrived'])}"
    return line


def draw_episodes(res: dict[str, Any], names: Any, title: str, out: str,
                  frames: list[tuple[int, np.ndarray]] = (), note: str | None = None) -> None:
    """The figure of a task that does not fly: frames of episode 0 (when rendered), the return and length of
    each episode, then every observation and action over the steps of each episode."""
    n_ep, n_obs = res["obs"].shape[0], res["obs"].shape[-1]
    action = res["action"].reshape(n_ep, res["action"].shape[1], -1)
    n_act = action.shape[-1]
    trace_rows = -(-(n_obs + n_act) // 2)
    heights = ([2.4] if frames else []) + [1.9] + [1.6] * trace_rows
    fig = _figure(figsize=(12, sum(heights) + 1.0))
    grid = fig.add_gridspec(len(heights), 1, height_ratios=heights)
    row = 0
    if frames:
        sub = grid[row].subgridspec(1, len(frames))
        for j, (t, img) in enumerate(frames):
            ax = fig.add_subplot(sub[0, j])
            ax.imshow(img)
            ax.set_title(f"episode 0, step {t}", fontsize=8)
            ax.axis("off")
        row += 1
    sub = grid[row].subgridspec(1, 2)
    ep = np.arange(n_ep)
    colors = _colors(n_ep)
    for j, (key, label) in enumerate((("return", "return"), ("length", "length (steps)"))):
        ax = fig.add_subplot(sub[0, j])
        ax.bar(ep, res[key], color=colors)
        if "arrived" in res and key == "return":
            for i in ep[res["arrived"]]:
                ax.annotate("arrived", (i, res[key][i]), ha="center", va="bottom", fontsize=7)
        ax.set_xlabel("episode")
        ax.set_ylabel(label)
        ax.set_xticks(ep)
        ax.grid(alpha=0.3, axis="y")
    row += 1
    sub = grid[row:].subgridspec(trace_rows, 2)
    panels = [(res["obs"][:, :, d], names[d] if names is not None and d < len(names) else f"obs[{d}]", 0)
              for d in range(n_obs)]
    panels += [(action[:, :, d], "action" if n_act == 1 else f"action[{d}]", 1) for d in range(n_act)]
    for p, (values, label, shift) in enumerate(panels):
        ax = fig.add_subplot(sub[p // 2, p % 2])
        for i in range(n_ep):
            alive = res["alive"][i][shift:]
            steps = np.flatnonzero(alive)
            ax.plot(steps, values[i][alive], lw=1.1, color=colors[i],
                    label=f"episode {i}: {int(res['length'][i])} steps" if p == 0 else None)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
        if p >= len(panels) - 2:
            ax.set_xlabel("step")
        if p == 0:
            ax.legend(fontsize=7, loc="best")
    fig.suptitle(title + (f"\n(no frames: {note})" if note else ""), fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    rundir.atomic_savefig(fig, out, dpi=100)


def _figure(**kw: Any) -> Any:
    """A matplotlib Figure that needs no pyplot and no backend switch (a notebook's inline backend stays)."""
    from matplotlib.figure import Figure

    return Figure(**kw)


def _colors(n: int) -> np.ndarray:
    import matplotlib

    return matplotlib.colormaps["tab10"](np.arange(n) % 10)


def run(args: argparse.Namespace) -> int:
    """Draw the episodes of a run's policy (greedy table, saved ppo/sac policy) or of a random policy (``--env``):
    flights for a quadcopter task, frames and per-episode plots for any other; returns a process exit code."""
    import sys

    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import selected_table
    from jaxrobo.training.run import resolve

    policy = None
    try:
        check_args(args)
        if args.run_dir and deep.is_deep_run(args.run_dir):
            args.table = args.table or 0
            args.policy = args.policy or "latest"
            spec, policy = _load_deep_run(args.run_dir, args.table, args.policy)
            q = None
            name = f"{spec.agent} {args.policy} policy"
        elif args.run_dir:
            if args.policy is not None:
                raise ConfigError(f"--policy {args.policy}: {args.run_dir} is a tabular run (its q-tables, not a "
                                  "ppo/sac policy); choose a table with --table N")
            spec, cfg, q = _load_run(args.run_dir)
            if args.table is None:
                args.table = selected_table(args.run_dir, q.shape[0])
            check_table(q, args.table, os.path.join(args.run_dir, "qtables.npz"))
            name = f"greedy {spec.config.agent}, table {args.table}"
        else:
            spec, q = resolve(args.env_id, args.preset or "default", check_memory=False), None
            args.table = 0
            name = "random policy (untrained)"
    except ConfigError as err:
        print(f"jaxrobo show: {err}", file=sys.stderr)
        return 2
    what = f"{name}, {os.path.basename(os.path.normpath(args.run_dir))}" if args.run_dir else name
    print(f"policy: {what}")
    if args.video is not None:
        return video(spec, args.video, args.seed, policy=policy, q=q, table=args.table)
    if flies(spec):
        res = fly(spec, q, args.table, args.episodes, args.seed, policy=policy)
        p = spec.env.default_params
        summary = ""
        if "arrived" in res:
            summary = f" - arrived {int(res['arrived'].sum())}/{len(res['arrived'])}"
        draw(res, f"{spec.env_id}: {what}{summary}", args.out, float(getattr(p, "goal_tolerance", 0.5)),
             float(getattr(p, "max_altitude", 0.0)) or None)
        print(f"wrote {args.out}")
        return 0
    if policy is None:
        policy = _table_policy(spec, q, args.table)
    res = episodes(spec, policy, args.episodes, args.seed)
    frames, note = render_frames(spec, res)
    names = getattr(spec.env.observation_space(), "names", None)
    draw_episodes(res, names, f"{spec.env_id}: {what} - {summary_line(res)} over {args.episodes} episodes",
                  args.out, frames, note)
    if note is not None:
        print(f"jaxrobo show: no frames drawn: {note}", file=sys.stderr)
    print(f"{args.episodes} episodes: {summary_line(res)}")
    print(f"wrote {args.out}")
    return 0
