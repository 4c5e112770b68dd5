"""A ``jaxrobo train --agent ppo|sac`` run stops promptly and keeps its work between evaluation points: each epoch
runs as several host iterations (:attr:`jaxrobo.deep.EpochPlan.chunks`) with the random keys the whole epoch
carries, so a run stopped between points and resumed ends bit for bit where the uninterrupted run does; a real
SIGINT to a run in a subprocess stops it before its end with a checkpoint past step 0, and ``--resume`` goes on
from there. CPU-sized: the ``tiny`` presets."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxrobo import deep
from jaxrobo.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CPC = "CartPoleContinuous-v0"
#: Two epochs, each cut in host iterations by an iteration_steps made small for the test: PPO 8 training steps of
#: 256 env steps per epoch, in 4 iterations of 512; SAC 62 actor steps of 8 env steps, in 31 iterations of 16.
RUNS = {"ppo": ({"total_steps": 4096, "iteration_steps": 512}, 512),
        "sac": ({"total_steps": 1024, "min_replay_size": 32, "iteration_steps": 16}, 16)}


def _args(agent: str, **changes) -> list[str]:
    return ["train", "--env", CPC, "--agent", agent, "--preset", "tiny", "--set", "episode_length=20",
            "--set", "eval_episodes=3", "--set", "num_evals=3", "--no-progress",
            *(arg for k, v in {**RUNS[agent][0], **changes}.items() for arg in ("--set", f"{k}={v}"))]


def _same_run(a: str, b: str) -> None:
    """The same trained policy and the same evaluations, bit for bit."""
    x, y = _arrays(os.path.join(a, "policy.npz")), _arrays(os.path.join(b, "policy.npz"))
    assert sorted(x) == sorted(y) and all(np.array_equal(x[k], y[k]) for k in x)
    with open(os.path.join(a, "evaluations.csv")) as f, open(os.path.join(b, "evaluations.csv")) as g:
        assert f.read() == g.read()


@pytest.mark.parametrize("agent", ["ppo", "sac"])
def test_the_default_run_splits_its_epochs_into_host_iterations(agent):
    """Each trainer's default run on the continuous cart-pole hands control back several times an epoch, in host
    iterations of at most its ``iteration_steps`` (SAC's grain is finer than PPO's: an env step costs it
    ``grad_updates_per_step`` gradient steps), so a stop keeps the work of the epoch in flight."""
    c = deep.resolve(CPC, agent).config
    plan = deep.epoch_plan(c)
    assert plan.chunks > 1 and plan.unit_steps <= max(c.iteration_steps, plan.step_size), plan
    assert plan.unit_steps * plan.chunks == plan.steps_per_epoch


def _status(path: str) -> dict:
    with open(os.path.join(path, "status.json")) as f:
        return json.load(f)


def _arrays(path: str) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.slow
@pytest.mark.parametrize("agent", ["ppo", "sac"])
def test_a_stop_between_points_resumes_bit_for_bit(agent, tmp_path, monkeypatch, capsys):
    spec = deep.resolve(CPC, agent, "tiny", {**RUNS[agent][0], "num_evals": 3})
    plan = deep.epoch_plan(spec.config)
    assert plan.chunks > 2 and plan.unit_steps == RUNS[agent][1]
    full, stopped = str(tmp_path / "full"), str(tmp_path / "stopped")
    assert main([*_args(agent), "--out", full]) == 0
    original = deep.LiveRun.chunk
    seen = []

    def chunk(self, p):
        original(self, p)
        seen.append((p.epochs_done, p.chunks_done))
        if (p.epochs_done, p.chunks_done) == (0, 1):
            os.kill(os.getpid(), signal.SIGTERM)  # StopOnSignal takes it: the run stops at the next iteration end

    with monkeypatch.context() as m:
        m.setattr(deep.LiveRun, "chunk", chunk)
        assert main([*_args(agent), "--out", stopped]) == 128 + signal.SIGTERM
    # Kept at the session's first iteration end (after the compile) and at the next, where the stop was seen.
    assert seen == [(0, 1), (0, 2)]
    at = plan.env_steps(0, 2)
    assert _status(stopped)["status"] == "interrupted" and f"at {at:,} env steps" in capsys.readouterr().err
    assert main(["train", "--resume", stopped]) == 0
    assert f"resuming after {at:,} env steps" in capsys.readouterr().out
    _same_run(full, stopped)
    with open(os.path.join(stopped, "summary.json")) as f:
        assert json.load(f)["resumed_after_env_steps"] == at
    # and the same as the run whose epochs are not split at all (one host iteration each)
    whole = str(tmp_path / "whole")
    unsplit = deep.resolve(CPC, agent, "tiny", {**RUNS[agent][0], "num_evals": 3, "iteration_steps": 1 << 30})
    assert deep.epoch_plan(unsplit.config).chunks == 1
    assert main([*_args(agent, iteration_steps=1 << 30), "--out", whole]) == 0
    _same_run(full, whole)


@pytest.mark.slow
def test_sigint_to_a_ppo_run_stops_it_between_points_and_resume_goes_on(tmp_path):
    """One epoch (num_evals=2) of 4 host iterations of 65,536 env steps: SIGINT once the first iteration's state is
    kept. The run ends before its end, exit 130, its checkpoint past 0 steps; --resume finishes from there."""
    out = str(tmp_path / "run")
    total = 4 * deep.PPOConfig().iteration_steps
    cmd = [sys.executable, "-m", "jaxrobo.cli", "train", "--env", CPC, "--agent", "ppo", "--preset", "tiny",
           "--set", "episode_length=20", "--set", "eval_episodes=3", "--set", "num_evals=2", "--total-steps",
           str(total), "--no-progress", "--out", out]
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT)
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                if _status(out).get("env_steps", 0) > 0:
                    break
            except (OSError, ValueError):
                pass
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)  # a bound for a loaded CI machine; the run itself is longer
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    status = _status(out)
    assert status["status"] == "interrupted" and status["signal"] == "SIGINT"
    kept = re.search(r"the trainer's state at ([\d,]+) env steps \(checkpoint\.npz\)", err)
    assert kept is not None, err
    steps = int(kept[1].replace(",", ""))
    assert 0 < steps < total and steps % deep.PPOConfig().iteration_steps == 0, err
    done = subprocess.run([sys.executable, "-m", "jaxrobo.cli", "train", "--resume", out, "--no-progress"], cwd=ROOT,
                          env=env, text=True, capture_output=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"resuming after {steps:,} env steps" in done.stdout
    with open(os.path.join(out, "summary.json")) as f:
        summary = json.load(f)
    assert summary["resumed_after_env_steps"] == steps and summary["env_steps"] == total


def test_a_stop_during_the_final_evaluation_keeps_the_finished_run(tmp_path, monkeypatch, capsys):
    """The signal comes while the last point is evaluated: the training is complete, so the run is written whole
    (exit 0) and one line says why it did not stop."""
    out = str(tmp_path / "run")
    original = deep.LiveRun.point

    def point(self, p):
        if p.epochs_done == p.plan.epochs:
            os.kill(os.getpid(), signal.SIGTERM)  # as if during the final evaluation, before its files are kept
        original(self, p)

    monkeypatch.setattr(deep.LiveRun, "point", point)
    assert main([*_args("ppo"), "--out", out]) == 0
    assert _status(out)["status"] == "complete" and os.path.isfile(os.path.join(out, "summary.json"))
    err = [ln for ln in capsys.readouterr().err.splitlines() if "final evaluation" in ln]
    assert err == ["jaxrobo train: SIGTERM during the final evaluation: the training was complete, so the run is "
                   "finished and written whole"]
