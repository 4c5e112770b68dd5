"""The ``jaxrobo`` command: ``train``, ``plot``, ``list``, and (when their modules are present) ``show``, ``sweep``,
``export``.

Examples::

    jaxrobo train --env CartPoleStayUp-v0 --agent qlearn --n-envs 256 --set alpha=0.3 --out runs/q
    jaxrobo train --env CartPoleStayUp-v0 --agent sarsa --n-envs 256 --out runs/s
    jaxrobo plot runs/q runs/s --out runs/q_vs_sarsa.png
    jaxrobo export runs/q --out policy/
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import os
import shutil
import sys
import time
from typing import Any, Iterator, Sequence

# Subcommands whose module provides configure_parser(parser) and run(args) -> int.
PLUGINS = {"show": ("jaxrobo.show",
                    "what a policy does, for any task: frames, returns, traces (flights for a quadcopter)"),
           "sweep": ("jaxrobo.training.sweep", "parameter sweep as one vmapped computation"),
           "export": ("jaxrobo.export", "a trained policy as policy.npz + policy.json and a numpy-only runner"),
           "eval": ("jaxrobo.evaluate", "a trained policy on shifted physics (robustness table and plot)"),
           "ros": ("jaxrobo.ros.cli", "ROS 1: an exported policy as a node, a MuJoCo stand-in for Gazebo")}


class _ClosedPipeSafe:
    """A standard stream that survives its reader going away (``jaxrobo train ... | head``): the first write
    that meets a closed pipe points the stream's descriptor at ``/dev/null`` and the command carries on, so the
    run, whose files are what it is for, is still written. Everything else is the wrapped stream's."""

    def __init__(self, stream: Any):
        self._stream = stream

    def _closed_pipe(self) -> None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())  # later writes and the interpreter's final flush go nowhere
        os.close(devnull)

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._closed_pipe()
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._closed_pipe()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def guard_streams() -> None:
    """Wrap ``sys.stdout`` and ``sys.stderr`` in :class:`_ClosedPipeSafe` (once; streams without a descriptor,
    such as pytest's captures, are left as they are)."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if isinstance(stream, _ClosedPipeSafe):
            continue
        try:
            stream.fileno()
        except (AttributeError, OSError, ValueError):
            continue
        setattr(sys, name, _ClosedPipeSafe(stream))


#: Default checkpoint cadence of ``jaxrobo train``: at the first chunk boundary this long after the last save.
CHECKPOINT_SECONDS = 300.0


#: ``jaxrobo train`` flags that are also settable with ``--set KEY=VALUE``.
TRAIN_FLAGS = (("n_envs", "--n-envs"), ("seed", "--seed"), ("nepisodes", "--nepisodes"), ("agent", "--agent"),
               ("total_steps", "--total-steps"), ("total_episodes", "--total-episodes"), ("devices", "--devices"))


def train_overrides(args: argparse.Namespace) -> dict:
    """``--set`` pairs merged with the flags; a key given both ways is refused (neither silently wins)."""
    from jaxrobo.core.config import merge_flags, parse_overrides

    overrides = merge_flags(parse_overrides(args.set or []), [(k, f, getattr(args, k)) for k, f in TRAIN_FLAGS])
    if args.agent is not None:
        del overrides["agent"]  # --agent goes to resolve(agent=...)
    return overrides


def _train(args: argparse.Namespace) -> int:
    """``jaxrobo train``: a fresh run into ``--out``, or ``--resume DIR``; exit 130/143 after SIGINT/SIGTERM with a
    resumable directory (:mod:`jaxrobo.io.rundir` has the rules of run directories).

    Several hosts: the same command on every host under ``jax.distributed`` (``$JAXROBO_COORDINATOR``,
    ``$JAXROBO_NUM_PROCESSES``, ``$JAXROBO_PROCESS_ID``: docs/scaling.md). The envs are split over every process's
    devices; process 0 writes the one run directory, the others compute with it and keep their copies of what it
    writes in a private temporary directory, removed at the end."""
    import jax

    from jaxrobo.core.config import ConfigError
    from jaxrobo.speed import sharding

    try:
        sharding.initialize_distributed()
    except sharding.JoinError as err:
        sharding.exit_after_join_error("jaxrobo train", err)
    except (ConfigError, ValueError, RuntimeError) as err:
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2
    if jax.process_count() > 1 and jax.process_index() != 0:
        import tempfile

        with tempfile.TemporaryDirectory(prefix="jaxrobo-process-") as private, \
                open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
            return _train_guarded(args, private)
    return _train_guarded(args, None)


def _private_copy(args: argparse.Namespace, private: str) -> argparse.Namespace:
    """The arguments of a process other than 0: what it writes goes to ``private``; a resumed run is read from
    where process 0 reads it (a file system the hosts share)."""
    copy = argparse.Namespace(**vars(args))
    copy.private_out = os.path.join(private, "run")
    copy.no_progress = True
    return copy


def _train_guarded(args: argparse.Namespace, private: str | None) -> int:
    if private is not None:
        args = _private_copy(args, private)
    try:
        with contextlib.ExitStack() as hold:  # the run directory's lock, released on any exit
            return _train_checked(args, hold)
    except KeyboardInterrupt:  # before the handlers are installed or after a second signal: nothing half-written
        print("jaxrobo train: interrupted", file=sys.stderr)
        return 130


def _train_spec(args: argparse.Namespace):
    """The run ``jaxrobo train`` is asked for and its directory: a new one from the flags (``--out`` checked),
    or the interrupted run of ``--resume DIR`` with its own ``config.yaml``. Raises ConfigError naming the flag."""
    from jaxrobo.io import rundir
    from jaxrobo.core.config import ConfigError
    from jaxrobo.task.registry import find
    from jaxrobo.training.run import resolve, spec_from_config

    resume = args.resume
    private = getattr(args, "private_out", None)  # a process other than 0 writes only there
    if args.checkpoint_every is not None and args.checkpoint_every < 0:
        raise ConfigError(f"--checkpoint-every={args.checkpoint_every}: expected an integer >= 0 (chunks; 0: "
                          "no saves on the way; still saved at the end and when interrupted)")
    if resume is None:
        overrides = train_overrides(args)
        env_id = args.env or "CartPoleStayUp-v0"
        found = find(env_id, where=f"--env {env_id}")  # imports a 'module:Id's module; a missing one names --env
        if ":" not in env_id:
            env_id = found.spec.id  # a deprecated name: said once (here), then the id it stands for
        spec = resolve(env_id, args.preset or "default", overrides, agent=args.agent)
        out = args.out or os.path.join("training_results",
                                       f"{spec.env_id}_{spec.config.agent}_{time.strftime('%Y%m%d-%H%M%S')}")
        if private is not None:
            return spec, private
        out = rundir.check_out(out, overwrite=args.overwrite)
        return spec, out
    refuse_resume_flags(resume, (("--agent", args.agent), ("--preset", args.preset),
                                 ("--n-envs", args.n_envs), ("--nepisodes", args.nepisodes),
                                 ("--total-steps", getattr(args, "total_steps", None)),
                                 ("--total-episodes", getattr(args, "total_episodes", None)),
                                 ("--seed", args.seed), ("--set", args.set), ("--out", args.out)), args.overwrite)
    resume = rundir.check_out(resume, resume=True, flag="--resume")
    is_sweep = os.path.exists(os.path.join(resume, "sweep_state.json"))
    if is_sweep and not os.path.exists(os.path.join(resume, "config.yaml")):  # else 'config file not found'
        raise ConfigError(f"--resume {resume}: is an interrupted sweep, not a train run; go on with "
                          f"jaxrobo sweep --resume {resume}")
    from jaxrobo.core.config import load_yaml

    saved = load_yaml(os.path.join(resume, "config.yaml"), where=f"--resume {resume}: config.yaml")
    if args.env is not None and args.env != saved.get("env_id"):
        raise ConfigError(f"--env {args.env}: the run in --resume {resume} is of env_id {saved.get('env_id')!r}; "
                          "with --resume, --env only confirms a 'module:Id' to import (drop it or give that id)")
    return spec_from_config(saved, where=f"--resume {resume}", trusted_env=args.env), resume


def _resumed_devices(cfg: Any, devices: int | None, resume: str) -> Any:
    """The loop settings a resumed run trains with: its own, or over ``--devices`` (``devices``, None when not
    given). Where the envs run, not what they compute: the checkpoint holds the whole carry, so a run may go on
    over another device count (say, on a host with fewer devices than it was split over); its ``config.yaml`` and
    the checkpoint's fingerprint keep the run's own setting. ConfigError naming the flag."""
    import jax

    from jaxrobo.core.config import ConfigError

    if devices is None:
        if cfg.devices > jax.device_count():
            raise ConfigError(f"--resume {resume}: the run was split over devices={cfg.devices} and there are only "
                              f"{jax.device_count()} here; --devices N goes on over N of them (0: every device)")
        return cfg
    if devices < 0:
        raise ConfigError(f"--devices={devices}: expected an integer >= 0 (0: every local device)")
    return dataclasses.replace(cfg, devices=devices)


def budget_line(cfg, trainer) -> str:
    """How the run is budgeted, in words, for the first line a training prints."""
    if trainer.budget == "steps":
        return (f"{cfg.n_envs} envs × {trainer.steps_per_env:,} steps (total_steps {cfg.total_steps:,}; episodes ≤ "
                f"{cfg.nsteps} steps, the first {cfg.nepisodes} of each env recorded)")
    if trainer.budget == "run_episodes":
        return (f"{cfg.n_envs} envs until the run has {cfg.total_episodes:,} episodes (episodes ≤ {cfg.nsteps} "
                f"steps, the first {cfg.nepisodes} of each env recorded)")
    return f"{cfg.n_envs} envs × {cfg.nepisodes} episodes ≤ {cfg.nsteps} steps"


def refuse_resume_flags(resume: str, flags: Sequence[tuple[str, Any]], overwrite: bool) -> None:
    """``--resume`` goes on with the run's own config.yaml and directory: any of ``flags`` (``(flag, value)``,
    given when the value is not None) or ``--overwrite`` is refused, naming them, before anything is read."""
    from jaxrobo.core.config import ConfigError

    given = [flag for flag, value in flags if value is not None] + (["--overwrite"] if overwrite else [])
    if given:
        raise ConfigError(f"--resume {resume}: the run goes on with its own config.yaml and directory; "
                          f"drop {', '.join(given)}")


def keep_live_scalars(live: str, staged: str) -> None:
    """Copy the event files :class:`jaxrobo.training.callbacks.LiveScalars` wrote into ``live`` while the run trained
    into the ``staged`` run that replaces it, beside the per-episode scalars written at the end: the finished run keeps
    the curve a user watched. A name the final writer also took (the same second) gets a ``.live`` suffix."""
    src, dst = os.path.join(live, "tensorboard"), os.path.join(staged, "tensorboard")
    if os.path.abspath(src) == os.path.abspath(dst) or not os.path.isdir(src):
        return
    os.makedirs(dst, exist_ok=True)
    for name in os.listdir(src):
        if name.startswith("events.") and os.path.isfile(os.path.join(src, name)):
            target = os.path.join(dst, name if not os.path.exists(os.path.join(dst, name)) else name + ".live")
            shutil.copy2(os.path.join(src, name), target)


def _deep_agent(args: argparse.Namespace) -> str | None:
    """``ppo`` or ``sac`` when the run asked for is one of Brax's trainers (``--agent``, ``--set agent=``, or a
    ``--resume`` of such a run), else None."""
    from jaxrobo import deep
    from jaxrobo.core.config import parse_overrides

    if deep.is_deep(args.agent):
        return args.agent
    if args.agent is None:
        try:
            sets = parse_overrides(args.set or [])
        except ValueError:  # the tabular path reports a malformed --set
            return None
        for key in ("agent", "agent.agent"):
            if deep.is_deep(sets.get(key)):
                return sets[key]
    if args.resume is not None and deep.is_deep_run(args.resume):
        return "resume"
    return None


def _deep_spec(args: argparse.Namespace, agent: str):
    """The deep run asked for, its directory and, for ``--resume``, its checkpoint
    (:class:`jaxrobo.deep.checkpoint.Saved`, None for a new run); ConfigError naming the flag or file."""
    from jaxrobo import deep
    from jaxrobo.deep import checkpoint
    from jaxrobo.io import rundir
    from jaxrobo.core.config import ConfigError, merge_flags, parse_overrides
    from jaxrobo.task.registry import find

    total_steps = getattr(args, "total_steps", None)
    if args.checkpoint_every is not None:
        raise ConfigError(f"--checkpoint-every: a {agent} run keeps a checkpoint at each of its evaluation points "
                          "(--set num_evals=N sets how many); drop the flag")
    # Flags of the tabular loop that Brax's trainer has no use for: refused, where they were silently ignored.
    run = "a resumed ppo/sac run" if agent == "resume" else f"--agent {agent}"
    if getattr(args, "devices", None) is not None:
        raise ConfigError(f"--devices: {run} trains on one device (Brax's trainer, max_devices_per_host=1); drop "
                          "the flag")
    if getattr(args, "total_episodes", None) is not None:
        raise ConfigError(f"--total-episodes: {run} trains for a number of env steps, not episodes; use "
                          "--total-steps N")
    if args.resume is not None:
        refuse_resume_flags(args.resume, (("--env", args.env),
                                          ("--agent", args.agent if agent != "resume" else None),
                                          ("--preset", args.preset), ("--n-envs", args.n_envs),
                                          ("--nepisodes", args.nepisodes), ("--total-steps", total_steps),
                                          ("--seed", args.seed), ("--set", args.set), ("--out", args.out)),
                            args.overwrite)
        resume = rundir.check_out(args.resume, resume=True, flag="--resume")  # or an --overwrite run pending
        from jaxrobo.io.results import load_config

        spec = deep.spec_from_config(load_config(resume), os.path.join(resume, "config.yaml"))
        saved = checkpoint.load(os.path.join(resume, rundir.CHECKPOINT), checkpoint.fingerprint(spec),
                                deep.epoch_plan(spec.config), spec.config.eval_episodes)
        return spec, resume, saved
    if args.nepisodes is not None:
        raise ConfigError(f"--nepisodes: --agent {agent} trains for a number of env steps, not episodes; use "
                          "--total-steps N")
    overrides = parse_overrides(args.set or [])
    for key in ("agent", "agent.agent"):
        value = overrides.pop(key, agent)
        if value != agent:
            raise ConfigError(f"agent given twice: --agent {agent} and --set {key}={value!r}; give it once")
    for alias in ("num_timesteps", "agent.num_timesteps"):
        if total_steps is not None and alias in overrides:
            raise ConfigError(f"total_steps given twice: --total-steps {total_steps} and --set {alias}="
                              f"{overrides[alias]!r} (the old name of total_steps); give it once")
    merge_flags(overrides, [("num_envs", "--n-envs", args.n_envs), ("seed", "--seed", args.seed),
                            ("total_steps", "--total-steps", total_steps)])
    env_id = args.env or "CartPoleContinuous-v0"
    find(env_id, where=f"--env {env_id}")
    spec = deep.resolve(env_id, agent, args.preset or "default", overrides)
    out = args.out or os.path.join("training_results", f"{spec.env_id}_{agent}_{time.strftime('%Y%m%d-%H%M%S')}")
    out = rundir.check_out(out, overwrite=args.overwrite)
    return spec, out, None


def _duration(seconds: float) -> str:
    seconds = int(round(max(seconds, 0.0)))
    h, rest = divmod(seconds, 3600)
    return f"{h}:{rest // 60:02d}:{rest % 60:02d}" if h else f"{rest // 60}:{rest % 60:02d}"


def deep_progress_line(point) -> str:
    """One line per evaluation point of a ppo/sac run: env steps done of the run's total, the training wall time,
    steps/s (:func:`jaxrobo.deep.eval_means`), the ETA of the training left, and the evaluation's mean return,
    length and success rate: the numbers of ``episode_stats.csv`` and TensorBoard."""
    from jaxrobo import deep

    e, total = point.row, point.plan.total_steps
    m = deep.eval_means(e)
    sps = m["env_steps_per_second"]
    # The ETA takes the pace since this session's first epoch ended (its compile excluded) once there is one.
    trained = [r for r in point.evaluations if r["env_steps"] > point.session_start_steps]
    pace = 0.0
    if len(trained) > 1:
        pace = (e["env_steps"] - trained[0]["env_steps"]) / max(e["seconds"] - trained[0]["seconds"], 1e-9)
    elif trained:
        pace = (e["env_steps"] - point.session_start_steps) / max(e["seconds"] - point.session_start_seconds, 1e-9)
    eta = (total - e["env_steps"]) / pace if pace > 0 else float("nan")
    line = (f"  {e['env_steps']:>11,}/{total:,} env steps ({100 * e['env_steps'] / total:3.0f} %)  "
            f"{_duration(e['seconds'])}  {sps:,.0f} steps/s  ETA {_duration(eta) if eta == eta else '?'}  "
            f"return {m['return_mean']:.2f}  length {m['length_mean']:.1f}")
    if "success_rate" in m:
        line += f"  success {m['success_rate']:.3f}"
    return line


def _train_deep(args: argparse.Namespace, agent: str, hold: contextlib.ExitStack) -> int:
    """``jaxrobo train --agent ppo|sac`` (or ``--resume`` of such a run): Brax's trainer on the env's Brax face, into
    a run directory that is checked before anything compiles, keeps the run's work at every evaluation point
    (:class:`jaxrobo.deep.LiveRun`) and is published whole when the run is done (:mod:`jaxrobo.deep`,
    :mod:`jaxrobo.io.rundir`). A stop (SIGINT/SIGTERM, an error) leaves the last point's checkpoint, latest and
    best policy: ``--resume`` goes on from there, ``jaxrobo show`` flies them."""
    import shlex

    from jaxrobo import deep
    from jaxrobo.deep import checkpoint
    from jaxrobo.io import rundir
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import write_config

    try:
        spec, out, saved = _deep_spec(args, agent)
        fingerprint = checkpoint.fingerprint(spec)
        hold.enter_context(rundir.claimed(out, overwrite=args.overwrite, resume=args.resume is not None))
    except ConfigError as err:
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2
    agent = spec.agent
    resume_cmd = f"jaxrobo train --resume {shlex.quote(out)}"
    live = out if saved is not None else rundir.live_dir(out)
    if saved is None:
        write_config(live, spec.to_dict())
    rundir.write_status(live, rundir.RUNNING, out=os.path.abspath(out), resume=resume_cmd)
    c, plan = spec.config, deep.epoch_plan(spec.config)
    going_on = saved is not None and (saved.epochs_done > 0 or saved.chunks_done > 0)
    print(f"{spec.env_id} · {agent} ({spec.preset}) · {c.num_envs} envs × {plan.total_steps:,} env steps "
          f"({plan.epochs} epochs), episodes ≤ {spec.episode_length} steps → {out}"
          + (f" (resuming after {plan.env_steps(saved.epochs_done, saved.chunks_done):,} env steps)"
             if going_on else ""))
    if live != out:
        print(f"checkpoints in {live} until the run is done", file=sys.stderr)
    keeper = deep.LiveRun(live, fingerprint, resume_cmd, saved, out=out)

    def on_point(point) -> None:
        keeper.point(point)
        if not args.no_progress:
            print(deep_progress_line(point), flush=True)

    def stopped(what: str, code: int, **fields) -> int:
        return _deep_stopped(live, out, resume_cmd, what, code, **fields)

    from jaxrobo.training import driver

    def notice(signum: int) -> None:
        import signal

        print(f"\n{signal.Signals(signum).name}: stopping at the end of the trainer's current step, its state kept "
              f"(within {driver.StopOnSignal.PATIENCE_SECONDS:.0f} s, else from the last state kept; again to quit "
              "at once)", file=sys.stderr)

    # SIGINT/SIGTERM: Brax's trainer cannot be paused, so it is stopped where it hands control back (the end of a
    # host iteration, a few of its training steps: the state is kept there). A host iteration that does not end
    # within StopOnSignal.PATIENCE_SECONDS (a long compiled step on a CPU) is abandoned: the process ends from the
    # watchdog thread, keeping the state kept last. A second signal quits at once the same way.
    watch = deep.TrainerWatch()

    def abandon(signum: int) -> bool:
        import signal

        with watch.lock:  # no file is being written while it is held
            if not watch.in_trainer:
                return False  # jaxrobo's own code runs: it sees the stop by itself, after keeping its state
            name = signal.Signals(signum).name
            code = stopped(f"{name}: stopped inside the trainer's step (it did not end within "
                           f"{driver.StopOnSignal.PATIENCE_SECONDS:.0f} s)", 128 + signum, signal=name)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)

    from jaxrobo.core.clock import command_seconds

    startup = command_seconds()  # imports, device discovery, config: the wall before the trainer starts
    try:
        with driver.StopOnSignal(notice, second="exit", abandon=abandon) as stop:
            result = deep.train(spec, on_point, should_stop=stop, resume=saved,
                                checkpoint_path=keeper.checkpoint_path, on_chunk=keeper.chunk, watch=watch)
    except deep.TrainingStopped as err:
        return stopped(f"{stop.name}: {err}", 128 + stop.signum, signal=stop.name)
    except SystemExit as err:  # the second signal (StopOnSignal's second="exit")
        name = stop.name or "signal"
        return stopped(f"{name} twice: quit during training", int(err.code or 1), signal=name)
    except KeyboardInterrupt:
        return stopped("interrupted during training", 130, signal="SIGINT")
    except ConfigError as err:  # the checkpoint's state does not fit the trainer (found at its first epoch)
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2
    except Exception as err:
        if rundir.is_resumable(live):  # the work of the last evaluation point is kept: say how to go on
            rundir.interrupted(live, out=out, resume=resume_cmd, prog="jaxrobo train", publish_live=True,
                               what=f"the run failed ({type(err).__name__}: {err}); {_kept(live)}")
        raise
    if result.stopped_at_end:
        print(f"jaxrobo train: {stop.name} during the final evaluation: the training was complete, so the run is "
              "finished and written whole", file=sys.stderr)

    def write(staged: str) -> None:
        deep.write_run(staged, result, live, {} if startup is None else {"startup_seconds": round(startup, 3)})
        rundir.write_status(staged, rundir.COMPLETE, env_steps=result.env_steps,
                            **({"resumed_after_env_steps": result.resumed_after_env_steps}
                               if result.resumed_after_env_steps else {}))

    try:
        rundir.publish_results(out, live, write)
    except Exception as err:  # noqa: BLE001 - the run's checkpoint and policy are in the live directory; say where
        rundir.interrupted(live, out=out, resume=resume_cmd, prog="jaxrobo train", publish_live=True,
                           what=f"writing the results failed ({type(err).__name__}: {err}); the trained policy is "
                                f"in {out}/{deep.POLICY_NPZ}")
        return 1
    s = result.summary()
    if s.get("target_met_in_training"):
        print(f"learning target met at the evaluation after {s['target_met_at_env_steps']:,} env steps: stopped "
              "before total_steps")
    print(f"{s['env_steps']:,} env steps in {s['train_seconds']:.1f} s of training ({s['env_steps_per_second']:,.0f} "
          f"steps/s, compile included; evaluations {s['eval_seconds']:.1f} s more)")
    line = (f"final evaluation: mean return {s['final_eval_mean_return']:.2f}, "
            f"mean length {s['final_eval_mean_length']:.1f}")
    if "final_eval_success_rate" in s:
        line += f", success {s['final_eval_success_rate']:.3f}"
    print(line + f" over {c.eval_episodes} fresh episodes (best: evaluation {s['best_evaluation']}, in best/)")
    print(f"results in {rundir.run_name(out)}")  # a resumed hidden sibling .NAME.*.partial was published as NAME
    return 0


def _kept(live: str) -> str:
    """What a stopped ppo/sac run kept in ``live``, in words: the trainer's state at the env steps its status
    names (where the last checkpoint was taken) and the last evaluation point's policies."""
    from jaxrobo.io import rundir

    steps = (rundir.read_status(live) or {}).get("env_steps")
    at = f" at {steps:,} env steps" if isinstance(steps, int) and not isinstance(steps, bool) else ""
    return f"the trainer's state{at} (checkpoint.npz) and the last evaluation point's latest and best policy are kept"


def _deep_stopped(live: str, out: str, resume_cmd: str, what: str, code: int, **fields) -> int:
    """A ppo/sac run stopped before it finished. Once it reached an evaluation point its checkpoint, latest and
    best policy are in ``live``: the run is marked interrupted (a staging ``live`` is moved into place as ``out``,
    replacing the old run that ``--overwrite`` named, as a stopped tabular run does) and ``resume_cmd`` goes on.
    Stopped before its first point, nothing trained exists: a new directory is marked interrupted (starting again
    is the way on), an old run that ``--overwrite`` was to replace stays as it was. Returns ``code``."""
    import shlex

    from jaxrobo.io import rundir

    if rundir.is_resumable(live):
        rundir.interrupted(live, out=out, resume=resume_cmd, prog="jaxrobo train", publish_live=True,
                           what=f"{what}; {_kept(live)}", **fields)
        return code
    again = f"jaxrobo train ... --out {shlex.quote(out)} --overwrite"
    if os.path.abspath(live) == os.path.abspath(out):
        rundir.interrupted(live, out=out, resume=again, prog="jaxrobo train",
                           what=f"{what}; stopped before its first evaluation point: nothing trained to keep",
                           **fields)
    else:
        rundir.discard(live)
        print(f"jaxrobo train: {what} before its first evaluation point; {out} still holds the run it had (not "
              f"replaced); to start again: {again}", file=sys.stderr)
    return code


@contextlib.contextmanager
def _resumable_on_error(live: str, out: str, resume_cmd: str) -> Iterator[None]:
    """An error after a checkpoint was saved (evaluating or writing the results of a finished run) leaves a run
    that ``resume_cmd`` (``jaxrobo train --resume OUT``) continues, and says so. The state of a run that replaces
    an old one (``--overwrite``) stays in its hidden staging sibling (:func:`jaxrobo.io.rundir.live_dir`), the old
    run whole until a complete run replaces it; ``--resume OUT`` finds the new run there
    (:func:`jaxrobo.io.rundir.pending`). The error is raised again."""
    from jaxrobo.io import rundir

    try:
        yield
    except Exception:
        if rundir.is_resumable(live):
            where = out if os.path.abspath(live) == os.path.abspath(out) else f"{live} (beside the old run)"
            print(f"jaxrobo train: the run failed after saving its checkpoint; {where} holds it; to go on: "
                  f"{resume_cmd}", file=sys.stderr)
        raise


@contextlib.contextmanager
def _landed(saves: Any) -> Iterator[None]:
    """On an error, wait for the checkpoint being written (:class:`jaxrobo.training.checkpoint.SaveInThread`)
    before the error goes on: :func:`_resumable_on_error` then finds it on disk. The error raised is the block's,
    not the save's."""
    try:
        yield
    except BaseException:
        with contextlib.suppress(Exception):
            saves.wait()
        raise


def _checkpoint_every(given: int | None, run_dir: str) -> int | None:
    """``--checkpoint-every`` of a resumed run: the one given now, else the one its ``status.json`` kept (a file
    read back: anything but an integer in 0..2^31-1 is ignored), else None (the time-based default)."""
    if given is not None:
        return given
    from jaxrobo.core.struct import INT32_MAX
    from jaxrobo.io import rundir

    kept = (rundir.read_status(run_dir) or {}).get("checkpoint_every")
    ok = isinstance(kept, int) and not isinstance(kept, bool) and 0 <= kept <= INT32_MAX
    return kept if ok else None


def _drop_if_unresumable(live: str, out: str):
    """An exit callback (``ExitStack.push``) for a new run: an error (a full or read-only disk) before its first
    checkpoint removes the directory it had created, so that no run directory is left without a checkpoint, and
    says so; one with a checkpoint is left to :func:`_resumable_on_error`."""
    from jaxrobo.io import rundir

    def on_exit(exc_type, _exc, _tb) -> bool:
        if exc_type is not None and issubclass(exc_type, Exception) and not rundir.is_resumable(live):
            rundir.discard(live)
            kept = "" if os.path.abspath(live) == os.path.abspath(out) else f" ({out} still holds the run it had)"
            print(f"jaxrobo train: the run failed before its first checkpoint; nothing was kept{kept}",
                  file=sys.stderr)
        return False
    return on_exit


def _train_checked(args: argparse.Namespace, hold: contextlib.ExitStack) -> int:
    import shlex

    from jaxrobo.training import checkpoint, driver
    from jaxrobo.io import rundir
    from jaxrobo.training.train import train
    from jaxrobo.training.trainer import Trainer
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import discretiser_arrays, save_run, write_config, write_episodes, write_summary
    from jaxrobo.tabular.learner import epsilon_schedule

    resume = args.resume
    agent = _deep_agent(args)
    if agent is not None:
        return _train_deep(args, agent, hold)
    try:
        spec, out = _train_spec(args)
        hold.enter_context(rundir.claimed(out, overwrite=args.overwrite, resume=resume is not None,
                                          flag="--out" if resume is None else "--resume"))
        cfg = spec.config if resume is None else _resumed_devices(spec.config, args.devices, resume)
        trainer = Trainer(spec.env, cfg)
        template = checkpoint.carry_template(trainer, spec.agent_params)
        fingerprint = checkpoint.carry_fingerprint(template, spec.to_dict())
        initial, start_chunk = None, 0
        if resume is not None:
            initial, start_chunk = checkpoint.load_checkpoint(os.path.join(out, rundir.CHECKPOINT), template,
                                                              fingerprint, max_chunks=trainer.max_chunks())
    except ConfigError as err:  # CheckpointError included
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2

    private = getattr(args, "private_out", None)
    # How to go on names the run directory (process 0's), not a process's private copy, removed at its exit.
    public = out if private is None else (args.resume or args.out)
    resume_cmd = (f"jaxrobo train --resume {shlex.quote(public)}" if public
                  else "jaxrobo train --resume <process 0's run directory>")
    if private is not None:  # a process other than 0: everything it writes stays in its private directory
        out = private
    live = out if (resume is not None and private is None) else rundir.live_dir(out)
    if resume is None:  # a failure before the first checkpoint leaves no run directory without one
        hold.push(_drop_if_unresumable(live, out))
    if resume is None or private is not None:
        write_config(live, spec.to_dict())
    n_chunks = trainer.max_chunks()
    # --checkpoint-every is kept in status.json, so that a resumed run saves as often as it was asked to.
    every_chunks = args.checkpoint_every if resume is None else _checkpoint_every(args.checkpoint_every, out)
    keep = {} if every_chunks is None else {"checkpoint_every": every_chunks}
    rundir.write_status(live, rundir.RUNNING, out=os.path.abspath(out), chunks_done=start_chunk, chunks=n_chunks,
                        resume=resume_cmd, **keep)
    checkpoint_path = os.path.join(live, rundir.CHECKPOINT)
    print(f"{spec.env_id} · {cfg.agent} ({spec.preset}) · {budget_line(cfg, trainer)} → {out}"
          + (f" (resuming after chunk {start_chunk} of {n_chunks})" if resume else ""))
    if spec.preset == "seed":
        print(seed_preset_note(spec))
    if spec.device_defaults:
        import jax

        print(f"sized to this {jax.devices()[0].device_kind}: "
              + ", ".join(f"{k}={v}" for k, v in spec.device_defaults.items())
              + f" (the {spec.preset} preset's on_gpu settings: an accelerator steps thousands of envs in about the "
                "time of a few; --n-envs or --set choose otherwise)")
    every = trainer.target_every()
    if every:
        print(f"stops once the learning target holds ({spec.env.learning_target.description}) on fresh greedy "
              f"episodes, checked every {every} chunks ({every * cfg.chunk_steps:,} steps per env); the budget is "
              "the cap (--set stop_at_target=false runs it whole)")
    print(f"running as {trainer.plan!r}")
    if getattr(spec.env, "randomised", False):
        # The plan's kernels take each env's drawn physics as per-env inputs, so randomisation keeps them.
        where = "the Pallas kernel takes each env's draw as per-env inputs" if trainer.plan.fused == "pallas" \
            else "the step runs on XLA (the plan runs no Pallas kernel)"
        print(f"randomise=true: each env draws its physics at every reset; {where}")
    if live != out:
        print(f"checkpoints in {live} until the run is done", file=sys.stderr)

    from jaxrobo.training import callbacks

    hooks = [callbacks.LiveScalars(live), callbacks.EvaluationLines(segments=not args.no_progress)]
    if not args.no_progress:
        hooks.insert(0, callbacks.ProgressBar())

    # The tables and records of the last checkpoint this process wrote, laid out as qtables.npz and records.npz: the
    # finished run links them.
    saved_files: dict[str, Any] = {}
    disc_arrays = discretiser_arrays(trainer.disc)
    epsilon = epsilon_schedule(spec.agent_params, cfg.nepisodes)

    def save(runner, chunks_done: int) -> None:
        saved_files.update(files=checkpoint.save_checkpoint(checkpoint_path, runner, chunks_done, fingerprint,
                                                            tables=disc_arrays, epsilon=epsilon), chunks=chunks_done)
        rundir.write_status(live, rundir.RUNNING, out=os.path.abspath(out), chunks_done=chunks_done,
                            chunks=n_chunks, resume=resume_cmd, **keep)

    # The checkpoint after the last chunk is written while the run computes its results (its copy of the carry
    # waits for the evaluation's reads: SaveInThread.hold); it lands before anything that needs it: the results
    # (which link its tables), an interrupted status, an error's hint.
    saves = checkpoint.SaveInThread(save)

    def notice(signum: int) -> None:
        import signal

        print(f"\n{signal.Signals(signum).name}: finishing the current chunk, then saving a checkpoint "
              "(again to quit without saving)", file=sys.stderr)

    # SIGINT/SIGTERM: finish the chunk, save, write what there is, exit 128 + signal; a second one exits at once.
    with _resumable_on_error(live, out, resume_cmd), driver.StopOnSignal(notice, second="exit") as stop, \
            _landed(saves):
        from jaxrobo.core.clock import command_seconds

        startup = command_seconds()  # imports, device discovery, config: the wall before the first compile
        result = train(spec.env, cfg, spec.agent_params, None, hooks, initial=initial, start_chunk=start_chunk,
                       checkpoint=saves, checkpoint_every=every_chunks or 0,
                       checkpoint_seconds=CHECKPOINT_SECONDS if every_chunks is None else None,
                       should_stop=driver.agreed_stop(stop),  # every process's answer under jax.distributed
                       trainer=trainer)  # the trainer whose carry was checked above: its trace of init is reused
        if not result.complete:
            # The checkpoint is saved (train called ``save``); the finished episodes and the status go with it,
            # the status last, and a staging directory is moved into place.
            saves.wait()
            write_episodes(live, result.returns, result.lengths, result.terminated, result.epsilon,
                           episodes_done=result.episodes_done)
            done_min = int(result.episodes_done.min())
            rundir.interrupted(live, out=out, resume=resume_cmd, prog="jaxrobo train", publish_live=True,
                               signal=stop.name, chunks_done=result.chunks_done, chunks=n_chunks,
                               episodes_done_min=done_min, nepisodes=cfg.nepisodes, **keep,
                               what=f"{stop.name}: stopped after chunk {result.chunks_done} of {n_chunks} "
                                    f"({done_min} of {cfg.nepisodes} episodes in every env)")
            return 128 + stop.signum

        t_write = time.perf_counter()
        # Once: summary.json and the lines below (a sort of every env's records), computed in a thread while the
        # episode files are written (65,536 envs on an H200 host: 0.3 s each, one after the other before).
        from concurrent.futures import ThreadPoolExecutor

        figures = ThreadPoolExecutor(1, thread_name_prefix="jaxrobo-summary")
        pending_summary = figures.submit(result.summary)

        def closing() -> checkpoint.Saved:
            """The files of the closing checkpoint (that of the result's carry), once written."""
            saves.wait()
            return saved_files["files"] if saved_files.get("chunks") == result.chunks_done else checkpoint.Saved()

        def tables() -> str | None:
            """The closing checkpoint's tables: the result's unless the run chose its final table after it."""
            return closing().tables if result.final_table_choice is None else None

        def write(staged: str) -> None:
            save_run(staged, result, spec.to_dict(), trainer.disc, summary=pending_summary.result, tables=tables,
                     records=lambda: closing().records)
            keep_live_scalars(live, staged)
            # The results' copy to the host, the figures and the files (the closing checkpoint's wait before the
            # evaluation is checkpoint_seconds).
            write_summary(staged, {**pending_summary.result(),
                                   "write_seconds": round(time.perf_counter() - t_write + result.copy_seconds, 3),
                                   "checkpoint_write_seconds": round(saves.seconds, 3),
                                   **({"startup_seconds": round(startup, 3)} if startup is not None else {})})
            rundir.write_status(staged, rundir.COMPLETE, chunks_done=result.chunks_done, chunks=n_chunks,
                                **({"resumed_after_chunk": start_chunk} if resume else {}))

        try:
            rundir.publish_results(out, live, write)
        finally:
            figures.shutdown(wait=True)  # a failed write still leaves no thread reading the result
        summary = pending_summary.result()
        # The results' copy to the host and the closing checkpoint's wait before the evaluation too: the wall's parts
        # add up to it but for the exit.
        write_seconds = time.perf_counter() - t_write + result.copy_seconds + result.checkpoint_seconds
    s = summary
    restored = f" ({s['restored_env_steps']:,} restored from the checkpoint)" if "restored_env_steps" in s else ""
    print(f"compiled in {s['compile_seconds']:.1f} s; {s['env_steps'] - s.get('restored_env_steps', 0):,} env steps "
          f"in {s['run_seconds']:.1f} s ({s['env_steps_per_second']:,.0f} steps/s){restored}; {s['useful_share']:.1%} "
          f"of the {s['env_slots']:,} env slots stepped were useful")
    if s.get("target_met_in_training"):
        print(f"learning target met after {s['target_met_at_env_steps']:,} env steps ({s['run_seconds']:.1f} s of "
              f"training, {s['target_checks']} check(s)): stopped before the budget's cap")
    elif s.get("target_checks"):
        print(f"learning target not met in {s['target_checks']} check(s): the whole budget ran")
    elif "target_checks" in s:
        print(f"the budget ended before the first learning-target check (every {s['target_every_chunks']} chunks)")
    total = command_seconds()
    print((f"wall {total:.1f} s: start-up {startup:.1f} s, " if total is not None and startup is not None else "wall: ")
          + f"compile {s['compile_seconds']:.1f} s, run {s['run_seconds']:.1f} s, evaluation "
          f"{s['eval_seconds']:.1f} s, writing {write_seconds:.1f} s")
    print(_training_figures(s))
    if "eval_mean_length" in s:
        print(f"greedy evaluation: mean length {s['eval_mean_length']:.1f}, mean return {s['eval_mean_return']:.1f} "
              f"over {result.eval_lengths.shape[0]} tables × {result.eval_lengths.shape[1]} episodes")
    if "eval_success_rate" in s:
        print(f"greedy arrival rate {s['eval_success_rate']:.1%} (best table {s['eval_best_table_success_rate']:.1%})")
    if "selected_table" in s:  # several tables: the best one (by the task's target), then on fresh episodes
        print(f"best table ({s['selected_table']}, by {s['best_ranked_by']}): mean length "
              f"{s['eval_best_table_mean_length']:.1f}, mean return {s['eval_best_table_mean_return']:.1f}; on "
              f"fresh episodes: mean length {s['selected_table_fresh_mean_length']:.1f}, mean return "
              f"{s['selected_table_fresh_mean_return']:.1f}")
    if s["physics_nan_episodes"]:
        print(f"warning: {s['physics_nan_episodes']} episodes ended on non-finite physics", file=sys.stderr)
    print(f"results in {rundir.run_name(out)}")  # a resumed hidden sibling .NAME.*.partial was published as NAME
    return 0


def _training_figures(s: dict) -> str:
    """The printed line of a run summary's training figures, each saying what it is of; the best window is the
    one the task's learning target calls best (``best_ranked_by``)."""
    figure = "return" if "best_100_window_mean_return" in s else "length"
    return (f"highest episode return {s['highest_reward_max']:.0f} · overall mean episode length "
            f"{s['overall_mean_length']:.1f} · best 100-episode window of mean {figure}: "
            f"{s[f'best_100_window_mean_{figure}']:.1f} ({s['best_ranked_by']})")


def _plot(args: argparse.Namespace) -> int:
    from jaxrobo.core.config import ConfigError
    from jaxrobo.pictures.plots import check_image_path, plot_runs, plot_scalars

    try:
        for d in args.runs:
            if not os.path.isdir(d):
                raise ConfigError(f"run directory {d!r} does not exist (or is not a directory)")
        from jaxrobo.core.struct import INT32_MAX

        if not 1 <= args.window <= INT32_MAX:
            raise ConfigError(f"--window {args.window}: must be an integer >= 1 and <= {INT32_MAX} (episodes averaged)")
        if args.labels is not None and len(args.labels) != len(args.runs):
            raise ConfigError(f"--labels: {len(args.labels)} labels for {len(args.runs)} runs; give one per run")
        out = args.out or os.path.join(args.runs[0], "scalars.png" if args.scalars else "rewards.png")
        check_image_path(out)
        if args.scalars:
            plot_scalars(args.runs, out, labels=args.labels)
        else:
            plot_runs(args.runs, out, labels=args.labels, window=args.window, x=args.x)
    except (FileNotFoundError, ValueError) as err:
        print(f"jaxrobo plot: {err}", file=sys.stderr)
        return 2
    print(out)
    return 0


def seed_preset_note(spec: Any) -> str:
    """What ``--preset seed`` is, printed when a run uses it: the seed's baseline, and what it costs in memory."""
    from jaxrobo.training.budget import estimate, format_bytes
    from jaxrobo.training.run import check_discretiser

    parts = estimate(spec.env, spec.config, check_discretiser(spec.env, spec.config))
    memory = ", ".join(f"{k} {format_bytes(v)}" for k, v in parts.items() if k != "total")
    return (f"preset seed: the seed's baseline, its own parameters and learners reproduced exactly to compare with; "
            f"not tuned to learn (the seed's cart-pole never does; the default preset is the one that learns); "
            f"memory about {format_bytes(parts['total'])} ({memory})")


def _list(args: argparse.Namespace) -> int:
    import jaxrobo
    from jaxrobo.task import registry
    from jaxrobo.core.config import ConfigError
    from jaxrobo.training.run import agent_presets

    print("environments:")
    for env_id in jaxrobo.registered():
        spec = jaxrobo.spec(env_id)
        try:
            presets = ", ".join(agent_presets(env_id)) or "-"
        except ConfigError as err:  # one broken agent YAML must not hide the other envs
            presets = "(agent YAML unreadable: see note)"
            print(f"  note: {env_id}: {err}", file=sys.stderr)
        print(f"  {env_id:28s} max {spec.max_episode_steps:5d} steps  presets: {presets:14s} {spec.description}")
    aliases = getattr(jaxrobo.task.registry, "ALIASES", {})
    for old, new in sorted(aliases.items()):
        print(f"  {old:28s} deprecated name of {new}")
    print("agents: " + ", ".join(registry.learners()) + " (tabular: Discrete actions)")
    from jaxrobo import deep

    print("        " + ", ".join(deep.AGENTS)
          + " (Brax's trainers: Box actions; presets in agents/configs/<agent>.yaml)")
    return 0


def _check(args: argparse.Namespace) -> int:
    """``jaxrobo check ID``: one line per check of the env; exit 1 if any fails, 2 for an unknown id."""
    from jaxrobo.check import check_env
    from jaxrobo.core.config import ConfigError

    try:
        results = check_env(args.env_id, quick=args.quick, seed=args.seed, long=args.long)
    except ConfigError as err:
        print(f"jaxrobo check: {err}", file=sys.stderr)
        return 2
    for r in results:
        print(r.line())
    failed = [r.name for r in results if not r.ok]
    print(f"{args.env_id}: " + (f"{len(failed)} of {len(results)} checks failed ({', '.join(failed)})" if failed
                                else f"all {len(results)} checks pass (or skip)"))
    return 1 if failed else 0


def build_parser() -> argparse.ArgumentParser:
    from jaxrobo.core.cliargs import Parser

    # a usage error is one line (the subcommands' parsers are of this class too: add_subparsers makes them so)
    parser = Parser(prog="jaxrobo", description="Train tabular agents on MJX robots, fast.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a tabular agent on many envs at once")
    p.add_argument("--env", default=None, help="environment id (see `jaxrobo list`; default CartPoleStayUp-v0)")
    p.add_argument("--agent", default=None,
                   help="qlearn | sarsa | expected_sarsa | double_q (Discrete ids); ppo | sac (Box ids, Brax)")
    p.add_argument("--preset", default=None,
                   help="parameter preset of the env's agent YAML: default | seed (default: default)")
    p.add_argument("--n-envs", type=int, default=None, help="environments (independent learners) run at once")
    p.add_argument("--nepisodes", type=int, default=None,
                   help="episodes per environment (the default budget); under --total-steps or --total-episodes, "
                        "how many episodes each environment records")
    p.add_argument("--total-steps", type=int, default=None, metavar="N",
                   help="step budget: N env steps for the whole run, all envs together (tabular: every env steps "
                        "ceil(N / n_envs), episodes restarting as they end: the batch stays full; ppo/sac: Brax's "
                        "num_timesteps, rounded up to whole epochs)")
    p.add_argument("--total-episodes", type=int, default=None, metavar="N",
                   help="episode budget of the whole run: every env steps until the run has finished N episodes "
                        "(with shared_table: the episodes the table learned from)")
    p.add_argument("--seed", type=int, default=None, help="random seed")
    p.add_argument("--devices", type=int, default=None, metavar="N",
                   help="split the envs over N devices (default 0: every local device, or the most that divide "
                        "n_envs; under jax.distributed, every host's); the tables are those of one device")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a parameter (repeatable)")
    p.add_argument("--out", default=None, help="run directory (default training_results/<env>_<agent>_<time>)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run already in --out (only once the new run is done or interrupted)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="go on with the interrupted run in DIR, from its config.yaml and checkpoint (no other "
                        "config flags; --devices N may place it over another device count)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                   help="save the training carry every N chunks (default: every ~5 minutes; 0: no saves on the "
                        "way); it is also always saved at the end of training, before the evaluation (a late "
                        "error then loses no training: --resume continues from it), and on SIGINT/SIGTERM")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_train)

    p = sub.add_parser("plot", help="reward and length per episode of one or more runs, to PNG")
    p.add_argument("runs", nargs="+", help="run directories written by `jaxrobo train`")
    p.add_argument("--out", default=None, help="PNG path (default <first run>/rewards.png)")
    p.add_argument("--labels", nargs="*", default=None, help="legend labels, one per run")
    p.add_argument("--window", type=int, default=10, help="moving-average window in episodes")
    p.add_argument("--x", default="auto", choices=("auto", "episode", "env_steps"),
                   help="x axis: episodes, or env steps of training (all envs; the common axis of a tabular and a "
                        "ppo/sac run); auto: env steps when a ppo/sac run is given")
    p.add_argument("--scalars", action="store_true",
                   help="draw the runs' TensorBoard scalars instead (RUN/tensorboard; works while a run trains: "
                        "default <first run>/scalars.png)")
    p.set_defaults(func=_plot)

    p = sub.add_parser("list", help="registered environments, presets and agents")
    p.set_defaults(func=_list)

    p = sub.add_parser("check", help="check an environment: spaces, purity, jit/vmap, keys, bounds, NaN guard")
    p.add_argument("env_id", metavar="ID", help="environment id (see `jaxrobo list`)")
    p.add_argument("--quick", action="store_true", help="shorter rollout; skip the MJX-vs-MuJoCo and Gymnasium checks")
    p.add_argument("--seed", type=int, default=0, help="seed of the keys the checks use")
    p.add_argument("--long", type=int, default=0, metavar="N",
                   help="also run N random steps per env (fresh episodes where one ends) and fail on any float of "
                        "the state beyond 1e6 in magnitude (finite but blown up)")
    p.set_defaults(func=_check)

    for name, (module, help_text) in PLUGINS.items():
        try:
            mod = importlib.import_module(module)
        except ImportError:
            continue
        p = sub.add_parser(name, help=help_text)
        mod.configure_parser(p)
        p.set_defaults(func=mod.run)
    return parser


def refuse_empty_flags(args: argparse.Namespace) -> None:
    """A string flag given as ``""`` (``--env ""``, ``--out ""``, ``--preset ""``) is refused, naming it: left
    alone it would read as "not given" and pick the default silently."""
    from jaxrobo.core.config import ConfigError

    for name, value in vars(args).items():
        if isinstance(value, str) and not value.strip() and name not in ("command",):
            raise ConfigError(f"--{name.replace('_', '-')} {value!r}: empty; give a value or leave the flag out")


#: Commands that never touch a device: they skip checking ``JAX_PLATFORMS`` (which starts a backend).
LIGHT_COMMANDS = ("list", "plot")


#: What the command sets in its own process where the user has not: XLA's default reserves 75 % of a GPU's memory
#: at the first array, which took 1.6 s of an H200 run's start and 0.3 s of its exit (measured, fresh processes);
#: a run allocates what it uses instead. ``XLA_PYTHON_CLIENT_PREALLOCATE=true`` restores XLA's default.
PROCESS_DEFAULTS = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}


def main(argv: Sequence[str] | None = None) -> int:
    from jaxrobo.core.clock import command_entered

    command_entered()  # the start-up of a command run inside another program counts from here
    argv, ros_args = list(sys.argv[1:] if argv is None else argv), []
    if argv[:1] == ["ros"]:  # a ROS node's own name:=value arguments (roslaunch's remappings, __name) are rospy's
        from jaxrobo_ros.system import split_ros_args

        argv, ros_args = split_ros_args(argv)
    args = build_parser().parse_args(argv)  # --help and usage errors exit here, before the cache is touched
    if ros_args:
        args.ros_args = ros_args
    from jaxrobo.core import environ

    if environ.running_cli():  # the command's own process only: a caller's streams and settings are the caller's
        for name, value in PROCESS_DEFAULTS.items():  # before any JAX backend starts (environ.check may start one)
            os.environ.setdefault(name, value)
        guard_streams()
        import warnings

        # A warning is one line naming the command (a deprecated --env, say), not Python's file:line and source.
        warnings.formatwarning = lambda message, category, *_, **__: \
            f"jaxrobo {args.command}: {category.__name__}: {message}\n"
    from jaxrobo.core.config import ConfigError

    try:  # every environment variable jaxrobo reads, and no flag given empty, before anything uses one
        environ.check(light=args.command in LIGHT_COMMANDS)
        refuse_empty_flags(args)
    except ConfigError as err:
        print(f"jaxrobo {args.command}: {err}", file=sys.stderr)
        return 2
    try:  # MJX is imported where a simulator first needs it (jaxrobo.physics.mjx_lean.LazyModule), never up front
        from jaxrobo.speed.cache import enable_or_warn

        enable_or_warn(f"jaxrobo {args.command}")
        return int(args.func(args) or 0)
    except KeyboardInterrupt:  # Ctrl-C where a command has no handler of its own (importing, plot, export, ...)
        print(f"jaxrobo {args.command}: interrupted", file=sys.stderr)
        return 130
    except ConfigError as err:  # a subcommand that does not catch it itself (show), e.g. JAX 64-bit mode is on
        print(f"jaxrobo {args.command}: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a full, read-only or vanished target: one line naming the path, not a traceback
        where = f" {err.filename}" if getattr(err, "filename", None) else ""
        print(f"jaxrobo {args.command}: cannot write{where}: {err.strerror or err}", file=sys.stderr)
        return 1


def entry() -> None:
    """The ``jaxrobo`` console script and ``python -m jaxrobo.cli``: :func:`main`, then the process ends without
    the interpreter's teardown (:mod:`jaxrobo.core.quick_exit`)."""
    from jaxrobo.core.quick_exit import exit_process

    exit_process(main())


if __name__ == "__main__":
    entry()
