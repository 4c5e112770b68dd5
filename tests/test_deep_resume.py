"""A ``jaxrobo train --agent ppo|sac`` run keeps its work: stopped (SIGTERM) at 60 % of its steps it leaves a
checkpoint, the latest and the best policy and live TensorBoard events; ``--resume`` reaches the same policy and
evaluations as the uninterrupted run, bit for bit; ``jaxrobo show`` flies a stopped run's policies; a checkpoint
that is damaged or of another run is refused. CPU-sized: the ``tiny`` presets with a few hundred steps."""
from __future__ import annotations

import csv
import json
import os
import shutil
import signal

import numpy as np
import pytest

from jaxrobo import deep
from jaxrobo.cli import main
from jaxrobo.core.config import ConfigError
from jaxrobo.io.results import read_scalars

CPC = "CartPoleContinuous-v0"
#: Five epochs of 256 env steps (PPO) / 96 after a 32-step prefill (SAC): the stop after epoch 3 is at 60 %.
ARGS = {"ppo": ("--total-steps", "1024"), "sac": ("--total-steps", "512", "--set", "min_replay_size=32")}
STOP_AFTER_EPOCH = 3


def _args(agent: str) -> list[str]:
    return ["train", "--env", CPC, "--agent", agent, "--preset", "tiny", "--set", "episode_length=20",
            "--set", "eval_episodes=3", "--set", "num_evals=6", *ARGS[agent], "--no-progress"]


def _arrays(path: str) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _rows(path: str, drop: tuple[str, ...] = ()) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(f)]


def _status(path: str) -> dict:
    with open(os.path.join(path, "status.json")) as f:
        return json.load(f)


# SAC's case re-checks with the other trainer what PPO's checks in the default tier: the slow tier runs it.
@pytest.fixture(scope="module", params=["ppo", pytest.param("sac", marks=pytest.mark.slow)])
def runs(request, tmp_path_factory):
    """An uninterrupted run, and the same run stopped by SIGTERM after epoch 3 (the scalars read from its event
    file while it was still training, at epoch 2, and a copy of it as it was when stopped), then resumed."""
    agent = request.param
    root = tmp_path_factory.mktemp(f"resume_{agent}")
    full, stopped, kept = str(root / "full"), str(root / "stopped"), str(root / "kept")
    assert main([*_args(agent), "--out", full]) == 0
    seen = {}
    original = deep.LiveRun.point

    def point(self, p):
        original(self, p)
        if p.epochs_done == 2:  # the run is training: what a reader of its event file finds now
            seen["scalars"] = read_scalars(os.path.join(self.live, deep.output.TENSORBOARD))
            seen["steps"] = [int(e["env_steps"]) for e in p.evaluations]
        if p.epochs_done == STOP_AFTER_EPOCH:
            os.kill(os.getpid(), signal.SIGTERM)  # StopOnSignal takes it: the run stops right after this point

    mp = pytest.MonkeyPatch()
    mp.setattr(deep.LiveRun, "point", point)
    try:
        assert main([*_args(agent), "--out", stopped]) == 128 + signal.SIGTERM
    finally:
        mp.undo()
    shutil.copytree(stopped, kept)
    assert main(["train", "--resume", stopped, "--no-progress"]) == 0
    return {"agent": agent, "full": full, "stopped": stopped, "kept": kept, "seen": seen}


@pytest.mark.slow
def test_a_stopped_run_keeps_its_checkpoint_and_policies(runs):
    kept = runs["kept"]
    status = _status(kept)
    assert status["status"] == "interrupted" and status["signal"] == "SIGTERM"
    assert status["resume"] == f"jaxrobo train --resume {runs['stopped']}"
    for name in ("checkpoint.npz", "policy.npz", "policy.json", "best/policy.npz", "best/policy.json",
                 "episode_stats.csv", "config.yaml"):
        assert os.path.isfile(os.path.join(kept, name)), name
    stats = _rows(os.path.join(kept, "episode_stats.csv"))
    assert len(stats) == STOP_AFTER_EPOCH + 1  # the point before training and one after each epoch
    with open(os.path.join(kept, "policy.json")) as f:
        net = json.load(f)
    assert net["evaluation"] == STOP_AFTER_EPOCH and net["env_steps"] == int(stats[-1]["env_steps"])
    plan = deep.epoch_plan(deep.spec_from_config(_config(kept)).config)
    assert int(stats[-1]["env_steps"]) == plan.prefill_steps + STOP_AFTER_EPOCH * plan.steps_per_epoch
    assert deep.load_policy(kept).net["agent"] == runs["agent"] == deep.load_policy(kept, "best").net["agent"]


def _config(run_dir: str) -> dict:
    from jaxrobo.io.results import load_config

    return load_config(run_dir)


@pytest.mark.slow
def test_tensorboard_scalars_are_readable_while_the_run_trains(runs):
    seen = runs["seen"]
    scalars = seen["scalars"]
    assert [step for step, _ in scalars["eval/return_mean"]] == seen["steps"]  # every point so far, none later
    assert "eval/env_steps_per_second" in scalars and "eval/length_mean" in scalars
    assert any(tag.startswith("training/") for tag in scalars)  # Brax's training metrics, as they come


def test_resume_reaches_the_uninterrupted_run_bit_for_bit(runs):
    full, resumed = runs["full"], runs["stopped"]
    a, b = _arrays(os.path.join(full, "policy.npz")), _arrays(os.path.join(resumed, "policy.npz"))
    assert sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)
    assert _rows(os.path.join(full, "evaluations.csv")) == _rows(os.path.join(resumed, "evaluations.csv"))
    # The same numbers at every point; only the wall time (``seconds``) is the two runs' own.
    drop = ("seconds",)
    assert (_rows(os.path.join(full, "episode_stats.csv"), drop)
            == _rows(os.path.join(resumed, "episode_stats.csv"), drop))
    status = _status(resumed)
    assert status["status"] == "complete" and status["resumed_after_env_steps"] > 0
    with open(os.path.join(resumed, "summary.json")) as f:
        summary = json.load(f)
    assert summary["resumed_after_env_steps"] == status["resumed_after_env_steps"]
    # TensorBoard of the resumed run: each point once, in order, the stopped session's included.
    steps = [s for s, _ in read_scalars(os.path.join(resumed, "tensorboard"))["eval/return_mean"]]
    assert steps == [int(r["env_steps"]) for r in _rows(os.path.join(resumed, "episode_stats.csv"))]


@pytest.mark.parametrize("which", ["latest", "best"])
def test_show_flies_a_stopped_runs_policies(runs, tmp_path, which, capsys):
    if runs["agent"] != "ppo":
        pytest.skip("one agent is enough: the policy files are the same kind")
    from jaxrobo import deep

    run, png = str(tmp_path / "run"), str(tmp_path / "trace.png")
    shutil.copytree(runs["kept"], run)
    # Only the chosen policy's files are read: the other one's parameters removed, it still flies.
    other = "best" if which == "latest" else "latest"
    os.remove(os.path.join(deep.policy_dir(run, other), deep.POLICY_NPZ))
    assert main(["show", run, "--policy", which, "--episodes", "2", "--out", png]) == 0
    out = capsys.readouterr().out
    assert f"policy: ppo {which} policy" in out and "2 episodes: mean return" in out and f"wrote {png}" in out
    assert os.path.getsize(png) > 0
    os.remove(os.path.join(deep.policy_dir(run, which), deep.POLICY_NPZ))  # and without them it is refused
    assert main(["show", run, "--policy", which, "--episodes", "2", "--out", png]) == 2
    assert f"no {os.path.relpath(os.path.join(deep.policy_dir(run, which), deep.POLICY_NPZ), run)}" \
        in capsys.readouterr().err


def test_a_damaged_or_foreign_checkpoint_is_refused(runs, tmp_path, capsys):
    if runs["agent"] != "ppo":
        pytest.skip("the checks do not depend on the agent")
    broken = str(tmp_path / "broken")
    shutil.copytree(runs["kept"], broken)
    path = os.path.join(broken, "checkpoint.npz")
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)
    assert main(["train", "--resume", broken]) == 2
    assert "cannot be read as plain arrays" in capsys.readouterr().err
    # Another run's checkpoint (another seed in its config.yaml): refused, naming what differs.
    other = str(tmp_path / "other")
    shutil.copytree(runs["kept"], other)
    cfg = os.path.join(other, "config.yaml")
    with open(cfg) as f:
        text = f.read()
    with open(cfg, "w") as f:
        f.write(text.replace("  seed: 0\n", "  seed: 1\n"))
    assert main(["train", "--resume", other]) == 2
    assert "refusing to resume: the configuration differs (train.seed" in capsys.readouterr().err
    assert main(["train", "--resume", runs["kept"], "--total-steps", "10"]) == 2
    assert "drop --total-steps" in capsys.readouterr().err


def test_total_steps_is_the_budget_and_num_timesteps_its_old_name(capsys):
    assert deep.resolve(CPC, "ppo", "tiny", {"num_timesteps": 640}).config.total_steps == 640
    assert deep.resolve(CPC, "sac", "tiny", {"agent.num_timesteps": 640}).config.total_steps == 640
    with pytest.raises(ConfigError, match="name the same setting"):
        deep.resolve(CPC, "ppo", "tiny", {"num_timesteps": 640, "total_steps": 512})
    assert main(["train", "--env", CPC, "--agent", "ppo", "--total-steps", "640", "--set", "num_timesteps=512"]) == 2
    assert "total_steps given twice" in capsys.readouterr().err


def test_a_checkpoint_of_non_finite_state_is_refused(runs, tmp_path, capsys):
    if runs["agent"] != "ppo":
        pytest.skip("the check does not depend on the agent")
    bad = str(tmp_path / "nan")
    shutil.copytree(runs["kept"], bad)
    path = os.path.join(bad, "checkpoint.npz")
    arrays = _arrays(path)
    name = next(k for k, v in arrays.items() if k.startswith("state_") and v.dtype.kind == "f" and v.size)
    arrays[name] = np.full_like(arrays[name], np.nan)
    np.savez(path, **arrays)
    assert main(["train", "--resume", bad]) == 2
    assert "holds non-finite values" in capsys.readouterr().err


def test_an_error_during_training_keeps_the_last_point_and_resume_goes_on(runs, tmp_path, capsys):
    if runs["agent"] != "ppo":
        pytest.skip("one agent is enough: the error path does not depend on it")
    out = str(tmp_path / "failed")
    original = deep.LiveRun.point

    def point(self, p):
        original(self, p)
        if p.epochs_done == 2:
            raise RuntimeError("disk on fire")

    mp = pytest.MonkeyPatch()
    mp.setattr(deep.LiveRun, "point", point)
    try:
        with pytest.raises(RuntimeError, match="disk on fire"):
            main([*_args("ppo"), "--out", out])
    finally:
        mp.undo()
    assert _status(out)["status"] == "interrupted"
    err = capsys.readouterr().err
    assert "the run failed (RuntimeError: disk on fire)" in err and f"jaxrobo train --resume {out}" in err
    assert main(["train", "--resume", out, "--no-progress"]) == 0
    a, b = _arrays(os.path.join(runs["full"], "policy.npz")), _arrays(os.path.join(out, "policy.npz"))
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_progress_line_csv_and_tensorboard_show_the_same_numbers(runs, capsys):
    """One definition of each number: the progress line of a point, its ``episode_stats.csv`` row and its
    TensorBoard scalars agree."""
    from jaxrobo.cli import deep_progress_line

    full = runs["full"]
    rows = _rows(os.path.join(full, "episode_stats.csv"))
    scalars = read_scalars(os.path.join(full, "tensorboard"))
    for tag, col in (("eval/return_mean", "return_mean"), ("eval/length_mean", "length_mean")):
        assert [s for s, _ in scalars[tag]] == [int(r["env_steps"]) for r in rows]
        assert np.allclose([v for _, v in scalars[tag]], [float(r[col]) for r in rows], rtol=1e-5)
    sps = [v for _, v in scalars["eval/env_steps_per_second"]]
    assert np.allclose(sps[1:], [int(r["env_steps"]) / float(r["seconds"]) for r in rows[1:]], rtol=1e-3)
    # The line of a point, rebuilt from the run's own evaluations.
    spec = deep.spec_from_config(_config(full))
    evaluations = []
    for r in _rows(os.path.join(full, "evaluations.csv")):
        i = int(r["evaluation"])
        if i == len(evaluations):
            evaluations.append({"env_steps": int(r["env_steps"]), "return": [], "length": []})
        evaluations[i]["return"].append(float(r["return"]))
        evaluations[i]["length"].append(float(r["length"]))
    for e, row in zip(evaluations, rows):
        e.update({"return": np.asarray(e["return"]), "length": np.asarray(e["length"]),
                  "seconds": float(row["seconds"])})
    plan = deep.epoch_plan(spec.config)
    point = deep.Point(spec, {}, plan, 3, evaluations[:4], [], None, None, evaluations[3]["seconds"], 0, 0.0)
    line = deep_progress_line(point)
    steps = evaluations[3]["env_steps"]
    assert f"{steps:,}/{plan.total_steps:,} env steps ({100 * steps / plan.total_steps:3.0f} %)" in line
    assert (f"return {float(rows[3]['return_mean']):.2f}" in line
            and f"length {float(rows[3]['length_mean']):.1f}" in line)
    assert f"{steps / evaluations[3]['seconds']:,.0f} steps/s" in line and "ETA " in line and "ETA ?" not in line
