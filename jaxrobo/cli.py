"""The ``jaxrobo`` command: ``train``, ``plot``, ``list``, and (when their modules are present) ``show``, ``sweep``.

Examples::

    jaxrobo train --env CartPoleStayUp-v0 --agent qlearn --n-envs 256 --set alpha=0.3 --out runs/q
    jaxrobo train --env CartPoleStayUp-v0 --agent sarsa --n-envs 256 --out runs/s
    jaxrobo plot runs/q runs/s --out runs/q_vs_sarsa.png
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
import time
from typing import Iterator, Sequence

# Subcommands whose module provides configure_parser(parser) and run(args) -> int.
PLUGINS = {"show": ("jaxrobo.show", "draw greedy flights of a trained quadcopter (top and side views)"),
           "sweep": ("jaxrobo.training.sweep", "parameter sweep as one vmapped computation")}


#: Default checkpoint cadence of ``jaxrobo train``: at the first chunk boundary this long after the last save.
CHECKPOINT_SECONDS = 300.0


#: ``jaxrobo train`` flags that are also settable with ``--set KEY=VALUE``.
TRAIN_FLAGS = (("n_envs", "--n-envs"), ("seed", "--seed"), ("nepisodes", "--nepisodes"), ("agent", "--agent"))


def train_overrides(args: argparse.Namespace) -> dict:
    """``--set`` pairs merged with the flags; a key given both ways is refused (neither silently wins)."""
    from jaxrobo.core.config import merge_flags, parse_overrides

    overrides = merge_flags(parse_overrides(args.set or []), [(k, f, getattr(args, k)) for k, f in TRAIN_FLAGS])
    if args.agent is not None:
        del overrides["agent"]  # --agent goes to resolve(agent=...)
    return overrides


def _train(args: argparse.Namespace) -> int:
    """``jaxrobo train``: a fresh run into ``--out``, or ``--resume DIR``; exit 130/143 after SIGINT/SIGTERM with a
    resumable directory (:mod:`jaxrobo.io.rundir` has the rules of run directories)."""
    try:
        with contextlib.ExitStack() as hold:  # the run directory's lock, released on any exit
            return _train_checked(args, hold)
    except KeyboardInterrupt:  # before the handlers are installed or after a second signal: nothing half-written
        print("jaxrobo train: interrupted", file=sys.stderr)
        return 130


def _train_spec(args: argparse.Namespace):
    """The run ``jaxrobo train`` is asked for and its directory: a new one from the flags (``--out`` checked),
    or the interrupted run of ``--resume DIR`` with its own ``config.yaml``. Raises ConfigError naming the flag."""
    import yaml

    from jaxrobo.io import rundir
    from jaxrobo.core.config import ConfigError
    from jaxrobo.task.registry import find
    from jaxrobo.training.run import resolve, spec_from_config

    resume = args.resume
    if args.checkpoint_every is not None and args.checkpoint_every < 0:
        raise ConfigError(f"--checkpoint-every={args.checkpoint_every}: expected an integer >= 0 (chunks; 0: "
                          "no saves on the way; still saved at the end and when interrupted)")
    if resume is None:
        overrides = train_overrides(args)
        env_id = args.env or "CartPoleStayUp-v0"
        find(env_id, where=f"--env {env_id}")  # imports the module of a 'module:Id'; a missing one names --env
        spec = resolve(env_id, args.preset or "default", overrides, agent=args.agent)
        out = args.out or os.path.join("training_results",
                                       f"{spec.env_id}_{spec.config.agent}_{time.strftime('%Y%m%d-%H%M%S')}")
        out = rundir.check_out(out, overwrite=args.overwrite)
        return spec, out
    given = [flag for flag, value in (("--agent", args.agent), ("--preset", args.preset),
                                      ("--n-envs", args.n_envs), ("--nepisodes", args.nepisodes),
                                      ("--seed", args.seed), ("--set", args.set), ("--out", args.out))
             if value is not None]
    given += ["--overwrite"] if args.overwrite else []
    if given:
        raise ConfigError(f"--resume {resume}: the run goes on with its own config.yaml and directory; "
                          f"drop {', '.join(given)}")
    resume = rundir.check_out(resume, resume=True, flag="--resume")
    from jaxrobo.core.config import load_yaml

    saved = load_yaml(os.path.join(resume, "config.yaml"), where=f"--resume {resume}: config.yaml")
    if args.env is not None and args.env != saved.get("env_id"):
        raise ConfigError(f"--env {args.env}: the run in --resume {resume} is of env_id {saved.get('env_id')!r}; "
                          "with --resume, --env only confirms a 'module:Id' to import (drop it or give that id)")
    return spec_from_config(saved, where=f"--resume {resume}", trusted_env=args.env), resume


def _progress_bar(nepisodes: int, initial):
    """A tqdm bar over episodes, starting where a resumed carry ``initial`` is."""
    import jax
    import numpy as np
    from tqdm.auto import tqdm

    done0 = 0 if initial is None else int(np.min(np.asarray(jax.device_get(initial.episode))))
    return tqdm(total=nepisodes, initial=min(done0, nepisodes), unit="ep", desc="training", dynamic_ncols=True)


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
    """The deep run asked for and its directory; ConfigError naming the flag."""
    from jaxrobo import deep
    from jaxrobo.io import rundir
    from jaxrobo.core.config import ConfigError, merge_flags, parse_overrides
    from jaxrobo.task.registry import find

    if args.resume is not None:
        raise ConfigError(f"--resume {args.resume}: a ppo/sac run cannot be resumed (Brax's trainers keep their state "
                          "inside one call); start it again with --out")
    if args.checkpoint_every is not None:
        raise ConfigError(f"--checkpoint-every: --agent {agent} runs do not checkpoint (Brax's trainer runs as one "
                          "call); drop the flag")
    if args.nepisodes is not None:
        raise ConfigError(f"--nepisodes: --agent {agent} trains for a number of env steps, not episodes; use "
                          "--set num_timesteps=N")
    overrides = parse_overrides(args.set or [])
    for key in ("agent", "agent.agent"):
        value = overrides.pop(key, agent)
        if value != agent:
            raise ConfigError(f"agent given twice: --agent {agent} and --set {key}={value!r}; give it once")
    merge_flags(overrides, [("num_envs", "--n-envs", args.n_envs), ("seed", "--seed", args.seed)])
    env_id = args.env or "CartPoleContinuous-v0"
    find(env_id, where=f"--env {env_id}")
    spec = deep.resolve(env_id, agent, args.preset or "default", overrides)
    out = args.out or os.path.join("training_results", f"{spec.env_id}_{agent}_{time.strftime('%Y%m%d-%H%M%S')}")
    out = rundir.check_out(out, overwrite=args.overwrite)
    return spec, out


def _train_deep(args: argparse.Namespace, agent: str, hold: contextlib.ExitStack) -> int:
    """``jaxrobo train --agent ppo|sac``: Brax's trainer on the env's Brax face, into a run directory that is
    checked before anything compiles and published whole (:mod:`jaxrobo.deep`, :mod:`jaxrobo.io.rundir`)."""
    import shlex

    import numpy as np

    from jaxrobo import deep
    from jaxrobo.io import rundir
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import write_config

    try:
        spec, out = _deep_spec(args, agent)
        hold.enter_context(rundir.claimed(out, overwrite=args.overwrite))
    except ConfigError as err:
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2
    live = rundir.live_dir(out)
    write_config(live, spec.to_dict())
    rundir.write_status(live, rundir.RUNNING, out=os.path.abspath(out))
    c = spec.config
    print(f"{spec.env_id} · {agent} ({spec.preset}) · {c.num_envs} envs × {c.num_timesteps:,} env steps, episodes "
          f"≤ {spec.episode_length} steps → {out}")

    def progress(row: dict) -> None:
        if args.no_progress:
            return
        line = (f"  {row['env_steps']:>12,} env steps  {row['seconds']:7.1f} s  return {np.mean(row['return']):9.2f}"
                f"  length {np.mean(row['length']):7.1f}")
        if "success" in row:
            line += f"  success {np.mean(row['success']):.3f}"
        print(line, flush=True)

    again = f"(a {agent} run does not resume) jaxrobo train ... --out {shlex.quote(out)} --overwrite"

    def stopped(what: str, code: int, **fields) -> int:
        return _deep_stopped(live, out, again, what, code, **fields)

    def notice(signum: int) -> None:
        import signal

        print(f"\n{signal.Signals(signum).name}: stopping at the trainer's next evaluation point; nothing trained "
              "is kept (again to quit at once)", file=sys.stderr)

    # SIGINT/SIGTERM: Brax's trainer cannot be paused, so it is stopped where it hands control back (its next
    # evaluation point); a second signal exits at once. Either way the run directory says "interrupted".
    from jaxrobo.training import driver

    try:
        with driver.StopOnSignal(notice, second="exit") as stop:
            result = deep.train(spec, progress, should_stop=stop)
    except deep.TrainingStopped as err:
        return stopped(f"{stop.name}: {err}; nothing trained was kept", 128 + stop.signum, signal=stop.name)
    except SystemExit as err:  # the second signal (StopOnSignal's second="exit")
        name = stop.name or "signal"
        return stopped(f"{name} twice: quit during training; nothing trained was kept", int(err.code or 1),
                       signal=name)
    except KeyboardInterrupt:
        return stopped("interrupted during training; nothing trained was kept", 130, signal="SIGINT")
    # The trained policy goes to disk first, so that no later error loses it.
    deep.save_policy(live, result.params, result.net)

    def write(staged: str) -> None:
        deep.write_run(staged, result)
        rundir.write_status(staged, rundir.COMPLETE, env_steps=result.env_steps)

    try:
        rundir.publish_results(out, live, write)
    except Exception as err:  # noqa: BLE001 - the policy is saved in the live directory; say where
        rundir.interrupted(live, out=out, resume=again, prog="jaxrobo train", publish_live=True,
                           what=f"writing the results failed ({type(err).__name__}: {err}); the trained policy is "
                                f"in {live}/{deep.POLICY_NPZ}")
        return 1
    s = result.summary()
    print(f"{s['env_steps']:,} env steps in {s['train_seconds']:.1f} s ({s['env_steps_per_second']:,.0f} steps/s, "
          f"compile included; evaluations {s['eval_seconds']:.1f} s more)")
    line = f"final evaluation: mean return {s['final_eval_mean_return']:.2f}, mean length {s['final_eval_mean_length']:.1f}"
    if "final_eval_success_rate" in s:
        line += f", success {s['final_eval_success_rate']:.3f}"
    print(line + f" over {c.eval_episodes} fresh episodes")
    print(f"results in {out}")
    return 0


def _deep_stopped(live: str, out: str, again: str, what: str, code: int, **fields) -> int:
    """A ppo/sac run stopped before it finished training: nothing trained exists to keep. A new directory
    (``live`` is ``out``) is marked ``interrupted``; an old run that ``--overwrite`` was to replace stays as it was
    (a stopped deep run cannot be resumed, so it must not replace a finished one) and the new run's staging
    directory is removed. Returns ``code``."""
    from jaxrobo.io import rundir

    if os.path.abspath(live) == os.path.abspath(out):
        rundir.interrupted(live, out=out, resume=again, prog="jaxrobo train", what=what, **fields)
    else:
        rundir.discard(live)
        print(f"jaxrobo train: {what}; {out} still holds the run it had (not replaced); to go on: {again}",
              file=sys.stderr)
    return code


@contextlib.contextmanager
def _resumable_on_error(live: str, out: str, resume_cmd: str) -> Iterator[None]:
    """An error after a checkpoint was saved (evaluating or writing the results of a finished run) leaves a run
    that ``resume_cmd`` (``jaxrobo train --resume OUT``) continues, and says so. The state of a run that replaces
    an old one (``--overwrite``) lives in a hidden staging sibling (:func:`jaxrobo.io.rundir.live_dir`): it is moved
    into place as OUT first, as an interrupted run is, so that ``--resume OUT`` finds the new run, not the old one.
    The error is raised again."""
    from jaxrobo.io import rundir

    try:
        yield
    except Exception:
        if rundir.is_resumable(live):
            if os.path.abspath(live) != os.path.abspath(out):
                try:
                    rundir.publish(live, out, overwrite=True)
                except OSError as err:
                    print(f"jaxrobo train: the run failed after saving its checkpoint in {live}, which could not be "
                          f"moved to {out} ({err}); move it there (the old run's place), then: {resume_cmd}",
                          file=sys.stderr)
                    raise
            print(f"jaxrobo train: the run failed after saving its checkpoint; {out} holds it; to go on: "
                  f"{resume_cmd}", file=sys.stderr)
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
    from jaxrobo.training import train as training
    from jaxrobo.core.config import ConfigError
    from jaxrobo.io.results import save_run, write_config, write_episodes

    resume = args.resume
    agent = _deep_agent(args)
    if agent is not None:
        return _train_deep(args, agent, hold)
    try:
        spec, out = _train_spec(args)
        hold.enter_context(rundir.claimed(out, overwrite=args.overwrite, resume=resume is not None,
                                          flag="--out" if resume is None else "--resume"))
        cfg = spec.config
        trainer = training.Trainer(spec.env, cfg)
        template = checkpoint.carry_template(trainer, spec.agent_params)
        fingerprint = checkpoint.carry_fingerprint(template, spec.to_dict())
        initial, start_chunk = None, 0
        if resume is not None:
            initial, start_chunk = checkpoint.load_checkpoint(os.path.join(out, rundir.CHECKPOINT), template,
                                                              fingerprint)
    except ConfigError as err:  # CheckpointError included
        print(f"jaxrobo train: {err}", file=sys.stderr)
        return 2

    live = out if resume is not None else rundir.live_dir(out)
    if resume is None:  # a failure before the first checkpoint leaves no run directory without one
        hold.push(_drop_if_unresumable(live, out))
    if resume is None:
        write_config(live, spec.to_dict())
    n_chunks = trainer.max_chunks()
    resume_cmd = f"jaxrobo train --resume {shlex.quote(out)}"
    # --checkpoint-every is kept in status.json, so that a resumed run saves as often as it was asked to.
    every_chunks = args.checkpoint_every if resume is None else _checkpoint_every(args.checkpoint_every, out)
    keep = {} if every_chunks is None else {"checkpoint_every": every_chunks}
    rundir.write_status(live, rundir.RUNNING, out=os.path.abspath(out), chunks_done=start_chunk, chunks=n_chunks,
                        resume=resume_cmd, **keep)
    checkpoint_path = os.path.join(live, rundir.CHECKPOINT)
    print(f"{spec.env_id} · {cfg.agent} ({spec.preset}) · {cfg.n_envs} envs × {cfg.nepisodes} episodes "
          f"≤ {cfg.nsteps} steps → {out}" + (f" (resuming after chunk {start_chunk} of {n_chunks})" if resume else ""))
    print(f"running as {trainer.plan!r}")
    if live != out:
        print(f"checkpoints in {live} until the run is done", file=sys.stderr)

    bar = None if args.no_progress else _progress_bar(cfg.nepisodes, initial)

    def progress(done: int, total: int, last_return: float) -> None:
        if bar is not None:
            bar.update(done - bar.n)
            bar.set_postfix(mean_reward=f"{last_return:.1f}")

    def save(runner, chunks_done: int) -> None:
        checkpoint.save_checkpoint(checkpoint_path, runner, chunks_done, fingerprint)
        rundir.write_status(live, rundir.RUNNING, out=os.path.abspath(out), chunks_done=chunks_done,
                            chunks=n_chunks, resume=resume_cmd, **keep)

    def notice(signum: int) -> None:
        import signal

        print(f"\n{signal.Signals(signum).name}: finishing the current chunk, then saving a checkpoint "
              "(again to quit without saving)", file=sys.stderr)

    # SIGINT/SIGTERM: finish the chunk, save, write what there is, exit 128 + signal; a second one exits at once.
    with _resumable_on_error(live, out, resume_cmd), driver.StopOnSignal(notice, second="exit") as stop:
        every = CHECKPOINT_SECONDS if every_chunks is None else None
        with trainer.plan.tracing():  # what train() does, with the trainer built above (its carry was checked)
            result = driver.run_training(trainer, spec.agent_params, None, progress, initial=initial,
                                         start_chunk=start_chunk, checkpoint=save,
                                         checkpoint_every=every_chunks or 0, checkpoint_seconds=every,
                                         should_stop=stop)
        if bar is not None:
            bar.close()
        if not result.complete:
            # The checkpoint is saved (train called ``save``); the finished episodes and the status go with it,
            # the status last, and a staging directory is moved into place.
            write_episodes(live, result.returns, result.lengths, result.terminated, result.epsilon,
                           episodes_done=result.episodes_done)
            done_min = int(result.episodes_done.min())
            rundir.interrupted(live, out=out, resume=resume_cmd, prog="jaxrobo train", publish_live=True,
                               signal=stop.name, chunks_done=result.chunks_done, chunks=n_chunks,
                               episodes_done_min=done_min, nepisodes=cfg.nepisodes, **keep,
                               what=f"{stop.name}: stopped after chunk {result.chunks_done} of {n_chunks} "
                                    f"({done_min} of {cfg.nepisodes} episodes in every env)")
            return 128 + stop.signum

        def write(staged: str) -> None:
            save_run(staged, result, spec.to_dict(), trainer.disc)
            rundir.write_status(staged, rundir.COMPLETE, chunks_done=result.chunks_done, chunks=n_chunks,
                                **({"resumed_after_chunk": start_chunk} if resume else {}))

        rundir.publish_results(out, live, write)
    s = result.summary()
    restored = f" ({s['restored_env_steps']:,} restored from the checkpoint)" if "restored_env_steps" in s else ""
    print(f"compiled in {s['compile_seconds']:.1f} s; {s['env_steps'] - s.get('restored_env_steps', 0):,} env steps "
          f"in {s['run_seconds']:.1f} s ({s['env_steps_per_second']:,.0f} steps/s){restored}")
    print(f"highest reward {s['highest_reward_max']:.0f} · overall mean length {s['overall_mean_length']:.1f} · "
          f"best 100 mean {s['best_100_mean_length']:.1f}")
    if "eval_mean_length" in s:
        print(f"greedy evaluation: mean length {s['eval_mean_length']:.1f}, mean return {s['eval_mean_return']:.1f} "
              f"over {result.eval_lengths.shape[0]} tables × {result.eval_lengths.shape[1]} episodes")
    if "eval_success_rate" in s:
        print(f"greedy arrival rate {s['eval_success_rate']:.1%} (best table {s['eval_best_table_success_rate']:.1%})")
    if "selected_table" in s:
        print(f"best table ({s['selected_table']}) on fresh episodes: mean length "
              f"{s['selected_table_fresh_mean_length']:.1f}, mean return {s['selected_table_fresh_mean_return']:.1f}")
    if s["physics_nan_episodes"]:
        print(f"warning: {s['physics_nan_episodes']} episodes ended on non-finite physics", file=sys.stderr)
    print(f"results in {out}")
    return 0


def _plot(args: argparse.Namespace) -> int:
    from jaxrobo.core.config import ConfigError
    from jaxrobo.pictures.plots import check_image_path, plot_runs

    try:
        for d in args.runs:
            if not os.path.isdir(d):
                raise ConfigError(f"run directory {d!r} does not exist (or is not a directory)")
        if args.window < 1:
            raise ConfigError(f"--window {args.window}: must be an integer >= 1 (episodes averaged)")
        if args.labels is not None and len(args.labels) != len(args.runs):
            raise ConfigError(f"--labels: {len(args.labels)} labels for {len(args.runs)} runs; give one per run")
        out = args.out or os.path.join(args.runs[0], "rewards.png")
        check_image_path(out)
        plot_runs(args.runs, out, labels=args.labels, window=args.window, x=args.x)
    except (FileNotFoundError, ValueError) as err:
        print(f"jaxrobo plot: {err}", file=sys.stderr)
        return 2
    print(out)
    return 0


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

    print("        " + ", ".join(deep.AGENTS) + " (Brax's trainers: Box actions; presets in agents/configs/<agent>.yaml)")
    return 0


def _check(args: argparse.Namespace) -> int:
    """``jaxrobo check ID``: one line per check of the env; exit 1 if any fails, 2 for an unknown id."""
    from jaxrobo.check import check_env
    from jaxrobo.core.config import ConfigError

    try:
        results = check_env(args.env_id, quick=args.quick, seed=args.seed)
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
    parser = argparse.ArgumentParser(prog="jaxrobo", description="Train tabular agents on MJX robots, fast.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a tabular agent on many envs at once")
    p.add_argument("--env", default=None, help="environment id (see `jaxrobo list`; default CartPoleStayUp-v0)")
    p.add_argument("--agent", default=None,
                   help="qlearn | sarsa | expected_sarsa | double_q (Discrete ids); ppo | sac (Box ids, Brax)")
    p.add_argument("--preset", default=None,
                   help="parameter preset of the env's agent YAML: default | seed (default: default)")
    p.add_argument("--n-envs", type=int, default=None, help="environments (independent learners) run at once")
    p.add_argument("--nepisodes", type=int, default=None, help="episodes per environment")
    p.add_argument("--seed", type=int, default=None, help="random seed")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a parameter (repeatable)")
    p.add_argument("--out", default=None, help="run directory (default training_results/<env>_<agent>_<time>)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the run already in --out (only once the new run is done or interrupted)")
    p.add_argument("--resume", default=None, metavar="DIR",
                   help="go on with the interrupted run in DIR, from its config.yaml and checkpoint (no other "
                        "config flags)")
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
    p.set_defaults(func=_plot)

    p = sub.add_parser("list", help="registered environments, presets and agents")
    p.set_defaults(func=_list)

    p = sub.add_parser("check", help="check an environment: spaces, purity, jit/vmap, keys, bounds, NaN guard")
    p.add_argument("env_id", metavar="ID", help="environment id (see `jaxrobo list`)")
    p.add_argument("--quick", action="store_true", help="shorter rollout; skip the MJX-vs-MuJoCo and Gymnasium checks")
    p.add_argument("--seed", type=int, default=0, help="seed of the keys the checks use")
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


def main(argv: Sequence[str] | None = None) -> int:
    from jaxrobo.physics.sim import quiet_imports

    with quiet_imports():
        import mujoco.mjx  # noqa: F401  (import once, silently: MJX prints warp import noise)
    args = build_parser().parse_args(argv)  # --help and usage errors exit here, before the cache is touched
    from jaxrobo.speed.cache import enable_or_warn

    enable_or_warn(f"jaxrobo {args.command}")
    from jaxrobo.core.config import ConfigError

    try:
        return int(args.func(args) or 0)
    except ConfigError as err:  # a subcommand that does not catch it itself (show), e.g. JAX 64-bit mode is on
        print(f"jaxrobo {args.command}: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # a full, read-only or vanished target: one line naming the path, not a traceback
        where = f" {err.filename}" if getattr(err, "filename", None) else ""
        print(f"jaxrobo {args.command}: cannot write{where}: {err.strerror or err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
