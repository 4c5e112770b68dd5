"""Sweeps lose nothing: --out is checked before compiling, results appear whole, finished groups survive an
interrupt, and a resumed sweep writes exactly what an uninterrupted one writes."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from jaxrobo.io import rundir
from jaxrobo.training import sweep
from jaxrobo.training.sweep import state as sweep_state
from jaxrobo.core.config import ConfigError
from stop_at_save import after_groups, signal_after_save

ENV = "CartPoleStayUp-v0"
FAST = {"xla_backend_optimization_level": 0}
# Two groups (number_splits changes the table's shape, so one compiled program each) of 2 configs × 2 seeds;
# the analytic cart-pole compiles in seconds, and chunks of 10 steps give every group several chunks to stop in.
ARGS = ["--env", ENV, "--agent", "qlearn", "--grid", "number_splits=4,6", "--grid", "alpha=0.1,0.5",
        "--seeds", "2", "--n-envs", "2", "--nepisodes", "3", "--nsteps", "30", "--set", "chunk_steps=10",
        "--set", "backend=analytic", "--set", "bins=null", "--eval-episodes", "1", "--no-plots"]
#: How a sweep ran, not what it found: timings, and the chunk a group resumed from.
TIMING = {"wall_seconds", "env_steps_per_second", "compile_seconds", "run_seconds", "eval_seconds", "write_seconds",
          "resumed_after_chunk"}


def _main(argv):
    """``jaxrobo sweep`` with fast compiles (the options are part of the sweep's saved settings, so every call
    passes the same)."""
    return sweep.main(argv, compiler_options=FAST)


def _untimed(obj):
    if isinstance(obj, dict):
        return {k: _untimed(v) for k, v in obj.items() if k not in TIMING}
    if isinstance(obj, list):
        return [_untimed(v) for v in obj]
    return obj


def _outputs(path):
    with open(os.path.join(path, "sweep.csv")) as f:
        csv_text = f.read()
    with open(os.path.join(path, "summary.json")) as f:
        summary = json.load(f)
    return csv_text, _untimed(summary)


def _finished_groups(path):
    ckpt = os.path.join(path, rundir.CHECKPOINT)
    if not os.path.exists(ckpt):
        return 0
    with np.load(ckpt, allow_pickle=False) as z:
        return int(z["finished"].size)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: the whole sweep in one go."""
    out = tmp_path_factory.mktemp("whole") / "sweep"
    assert _main([*ARGS, "--out", str(out)]) == 0
    assert sorted(os.listdir(out)) == ["status.json", "summary.json", "sweep.csv"]  # no state, no staging left
    assert rundir.is_complete(str(out))
    assert not [p for p in os.listdir(out.parent) if p.endswith(".partial")]
    return out


def test_cli_interrupt_by_signal_then_resume(uninterrupted, tmp_path, capsys):
    """A SIGTERM after the first group: exit 143, one line, the group saved; --resume finishes the sweep with
    the same sweep.csv and summary.json as the uninterrupted run (timings aside)."""
    out = tmp_path / "sweep"
    with signal_after_save(sweep_state, signal.SIGTERM, after_groups(1)):  # the sweep stops before group 2
        assert _main([*ARGS, "--out", str(out)]) == 143
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "SIGTERM" in err[0] and "1 of 2 groups" in err[0] and f"--resume {out}" in err[0]
    assert _finished_groups(out) == 1
    assert rundir.read_status(str(out))["status"] == rundir.INTERRUPTED
    assert not rundir.is_complete(str(out)) and rundir.is_resumable(str(out))
    assert not os.path.exists(out / "sweep.csv") and not os.path.exists(out / "summary.json")

    # The saved settings are the sweep's: flags that differ are refused, before anything runs.
    for flags, name in ((["--seeds", "3"], "--seeds"), (["--grid", "alpha=0.2"], "--grid"),
                        (["--set", "chunk_steps=20"], "--set"), (["--overwrite"], "--overwrite"),
                        (["--out", str(tmp_path / "elsewhere")], "--out")):
        assert _main(["--resume", str(out), *flags]) == 2
        assert name in capsys.readouterr().err
    assert _finished_groups(out) == 1 and not os.path.exists(tmp_path / "elsewhere")

    # Repeating a flag with its saved value is fine.
    assert _main(["--resume", str(out), "--seeds", "2", "--no-plots"]) == 0
    printed = capsys.readouterr().out
    assert "group 1/2 [number_splits=4]: finished before" in printed
    assert _outputs(out) == _outputs(uninterrupted)
    assert sorted(os.listdir(out)) == ["status.json", "summary.json", "sweep.csv"]
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]
    assert _main(["--resume", str(out)]) == 2
    assert "complete, nothing to resume" in capsys.readouterr().err


def test_cli_sigint_in_a_subprocess(uninterrupted, tmp_path, capsys):
    """A real Ctrl-C while the second group runs: exit 130 and one line; the first group is kept, the second
    abandoned, and --resume gives the uninterrupted sweep's numbers."""
    out = tmp_path / "sweep"
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    script = ("import sys, jax\n"
              f"jax.config.update('jax_compilation_cache_dir', {jax.config.jax_compilation_cache_dir!r})\n"
              "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0.5)\n"
              "from jaxrobo.training import sweep\n"
              f"sys.exit(sweep.main({[*ARGS, '--out', str(out)]!r}, compiler_options={FAST!r}))\n")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while _finished_groups(out) < 1 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, "the sweep ended before it could be interrupted"
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stdout + stderr
    lines = [line for line in stderr.strip().splitlines() if line.startswith("jaxrobo sweep")]
    assert len(lines) == 1 and "SIGINT" in lines[0] and "--resume" in lines[0], stderr
    assert "Traceback" not in stderr
    assert _finished_groups(out) == 1
    assert _main(["--resume", str(out)]) == 0  # with the saved --no-plots
    assert sorted(os.listdir(out)) == sorted(os.listdir(uninterrupted))
    csv_text, summary = _outputs(out)
    ref_csv, ref_summary = _outputs(uninterrupted)
    assert csv_text == ref_csv
    assert {k: v for k, v in summary.items() if k != "argv"} == {k: v for k, v in ref_summary.items() if k != "argv"}


def _plan(**changes):
    kw = dict(points=[{"number_splits": s, "alpha": a} for s in (4, 6) for a in (0.1, 0.5)], seeds=[0, 1],
              agent="qlearn", overrides={"n_envs": 2, "nepisodes": 3, "nsteps": 30, "chunk_steps": 10,
                                         "backend": "analytic", "bins": None}, eval_episodes=1, compiler_options=FAST)
    kw.update(changes)
    return sweep.plan_sweep(ENV, **kw)


def test_library_stop_hook_and_resume(uninterrupted, tmp_path, monkeypatch):
    """run_plan's should_stop abandons the running group; the state refuses another sweep or other code; the
    resumed rows are the uninterrupted CLI sweep's rows."""
    state = str(tmp_path / "state")
    os.makedirs(state)
    lines: list[str] = []
    plan = _plan()
    with pytest.raises(sweep.SweepInterrupted) as info:
        sweep.run_plan(plan, log=lines.append, state_dir=state,
                       should_stop=lambda: any(line.startswith("group 2/") for line in lines))
    assert (info.value.done, info.value.total) == (1, 2)
    assert _finished_groups(state) == 1
    with pytest.raises(ConfigError, match="seeds differ"):
        sweep.run_plan(_plan(seeds=[0, 2]), state_dir=state)
    with pytest.raises(ConfigError, match="groups, points differ"):
        sweep.run_plan(_plan(points=[{"number_splits": 4, "alpha": 0.1}]), state_dir=state)
    code_version = sweep_state.code_version
    monkeypatch.setattr(sweep_state, "code_version", lambda: {**code_version(), "jaxrobo_sources": "edited"})
    with pytest.raises(ConfigError, match="other code"):
        sweep.run_plan(plan, state_dir=state)
    monkeypatch.setattr(sweep_state, "code_version", code_version)
    assert _finished_groups(state) == 1

    lines.clear()
    result = sweep.run_plan(plan, log=lines.append, state_dir=state)
    assert sum("finished before" in line for line in lines) == 1
    sweep.write_csv(result, str(tmp_path / "resumed.csv"))
    with open(tmp_path / "resumed.csv") as f:
        assert f.read() == _outputs(uninterrupted)[0]


def test_out_refused_before_compiling(uninterrupted, tmp_path, monkeypatch, capsys):
    """An existing file, a parent that is a file, a non-empty directory: exit 2 with one line naming --out and
    the flag that would allow it; nothing compiles and nothing is written."""

    def no_compile(*_a, **_k):
        raise AssertionError("compiled despite a refused --out")

    monkeypatch.setattr(sweep.GroupRunner, "run", no_compile)
    a_file = tmp_path / "file"
    a_file.write_text("keep me")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    done = tmp_path / "done"
    shutil.copytree(uninterrupted, done)
    cases = [(a_file, "existing file"), (a_file / "sub", "is a file"), (foreign, "choose another path"),
             (done, "--overwrite")]
    before = sorted(os.listdir(tmp_path))
    for out, why in cases:
        assert _main([*ARGS, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"jaxrobo sweep: --out {out}") and why in err[0], err
    assert _main([*ARGS, "--resume", str(done)]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == before
    assert a_file.read_text() == "keep me" and os.listdir(foreign) == ["notes.txt"]
    assert _outputs(done) == _outputs(uninterrupted)


def test_overwrite_replaces_a_sweep(uninterrupted, tmp_path):
    """--overwrite replaces a finished sweep by the new one (here its first group alone: the same program)."""
    out = tmp_path / "sweep"
    shutil.copytree(uninterrupted, out)
    one_group = [a if a != "number_splits=4,6" else "number_splits=4" for a in ARGS]
    assert _main([*one_group, "--out", str(out), "--overwrite"]) == 0
    csv_text, summary = _outputs(out)
    assert summary["n_rows"] == 4 and len(csv_text.strip().splitlines()) == 5
    assert csv_text.splitlines()[1:] == _outputs(uninterrupted)[0].splitlines()[1:5]
    assert sorted(os.listdir(out)) == ["status.json", "summary.json", "sweep.csv"]
    assert rundir.is_complete(str(out))
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]


@pytest.mark.parametrize("error", [RuntimeError("device lost"), KeyboardInterrupt()], ids=["crash", "ctrl-c"])
def test_error_mid_group_keeps_finished_groups(error, uninterrupted, tmp_path, monkeypatch, capsys):
    """An error in the second group (or a second Ctrl-C, which drops the group at once): the first group stays
    saved, a line says how to go on, and --resume finishes the sweep as if nothing happened."""
    out = tmp_path / "sweep"
    run = sweep.GroupRunner.run
    calls = []

    def fail_second(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise error
        return run(self, *args, **kwargs)

    monkeypatch.setattr(sweep.GroupRunner, "run", fail_second)
    if isinstance(error, KeyboardInterrupt):
        assert _main([*ARGS, "--out", str(out)]) == 130
    else:
        with pytest.raises(RuntimeError, match="device lost"):
            _main([*ARGS, "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--resume {out}" in err[0]
    status = rundir.read_status(str(out))
    assert status["status"] == rundir.INTERRUPTED
    assert isinstance(error, KeyboardInterrupt) or "device lost" in status["error"]
    assert _finished_groups(out) == 1
    monkeypatch.setattr(sweep.GroupRunner, "run", run)
    assert _main(["--resume", str(out)]) == 0
    assert _outputs(out) == _outputs(uninterrupted)


def test_interrupted_overwrite_keeps_the_old_run(uninterrupted, tmp_path, capsys):
    """With --overwrite the state lives in a hidden sibling: an interrupt leaves the old run whole, and resuming
    the sibling replaces the old run and removes the sibling."""
    out = tmp_path / "sweep"
    shutil.copytree(uninterrupted, out)
    (out / "summary.json").write_text('{"old": true}')  # tells the old run from the new one
    with signal_after_save(sweep_state, signal.SIGINT, after_groups(1)):
        assert _main([*ARGS, "--out", str(out), "--overwrite"]) == 130
    last = capsys.readouterr().err.strip().splitlines()[-1]
    (live,) = [p for p in os.listdir(tmp_path) if p.startswith(".sweep.") and p.endswith(".partial")]
    live = str(tmp_path / live)
    assert f"--resume {live}" in last
    assert json.loads((out / "summary.json").read_text()) == {"old": True}
    assert rundir.read_status(live)["out"] == str(out) and _finished_groups(live) == 1
    assert _main(["--resume", live]) == 0
    assert _outputs(out) == _outputs(uninterrupted)
    assert not os.path.exists(live) and os.listdir(tmp_path) == ["sweep"]


def test_a_stop_inside_a_group_saves_its_carry_and_resume_goes_on_from_that_chunk(uninterrupted, tmp_path,
                                                                                    capsys):
    """A stop after two chunks of the first group saves that group's carry (group_0.npz); --resume goes on from
    chunk 2, runs only the chunks left, and writes the uninterrupted sweep's sweep.csv byte for byte. A damaged
    group carry is refused naming the file and how to start the group over."""
    state = str(tmp_path / "state")
    os.makedirs(state)
    plan = _plan()
    chunks: list[int] = []
    with pytest.raises(sweep.SweepInterrupted) as info:
        sweep.run_plan(plan, state_dir=state, progress=lambda p: chunks.append(p.chunks_done),
                       should_stop=lambda: len(chunks) == 2)
    assert info.value.partial == (0, 2, 9) and "group 1 saved after chunk 2 of 9" in info.value.where
    assert _finished_groups(state) == 0 and os.path.exists(sweep_state.group_carry_path(state, 0))
    kept = str(tmp_path / "group_0_kept.npz")
    shutil.copy(sweep_state.group_carry_path(state, 0), kept)

    lines: list[str] = []
    chunks.clear()
    reports: list = []
    result = sweep.run_plan(plan, log=lines.append, state_dir=state,
                            progress=lambda p: chunks.append(p.chunks_done) or reports.append(p))
    assert any("group 1 goes on from its last saved chunk" in line for line in lines), lines
    assert any("going on from chunk 2 of 9" in line for line in lines), lines
    assert any("more restored from chunk 2" in line for line in lines), lines  # its speed: this process's steps
    assert chunks[0] == 3  # the first chunk run is the third: chunks 1 and 2 came from the carry
    assert result.groups[0]["resumed_after_chunk"] == 2 and "resumed_after_chunk" not in result.groups[1]
    # The rates count this process's work: the restored carry's steps are its starting point, not its speed.
    first = reports[0]
    assert first.useful_before > 0 and first.useful_steps > first.useful_before
    assert first.steps_per_second == pytest.approx((first.useful_steps - first.useful_before) / first.seconds)
    assert not os.path.exists(sweep_state.group_carry_path(state, 0))  # dropped once the group was finished
    sweep.write_csv(result, str(tmp_path / "resumed.csv"))
    with open(tmp_path / "resumed.csv") as f:
        assert f.read() == _outputs(uninterrupted)[0]

    # A damaged carry, or another group's, is refused before any group is set up or compiled.
    bad = str(tmp_path / "bad")
    os.makedirs(bad)
    sweep_state.open_state(bad, plan)
    with open(sweep_state.group_carry_path(bad, 0), "wb") as f:
        f.write(b"PK\x03\x04 not an npz")
    lines.clear()
    with pytest.raises(ConfigError, match=r"group_0\.npz.*remove .*group_0\.npz to run group 1 from its first"):
        sweep.run_plan(plan, state_dir=bad, log=lines.append)
    assert not any(line.startswith("group ") for line in lines), lines
    os.remove(sweep_state.group_carry_path(bad, 0))
    shutil.copy(kept, sweep_state.group_carry_path(bad, 1))  # group 1's carry saved as group 2's
    with pytest.raises(ConfigError, match=r"group_1\.npz: refusing to resume from it: the configuration differs "
                                          r"\(group: 0 in the checkpoint vs 1 now\).*to run group 2 from its first"):
        sweep.run_plan(plan, state_dir=bad, log=lines.append)
    assert not any(line.startswith("group ") for line in lines), lines


def test_a_sweep_group_trains_through_train_and_its_callbacks(uninterrupted, tmp_path, monkeypatch):
    """Every group is one train() of a population: a Callback handed to run_plan hears each group's start (its
    trainer, its carry), every chunk and the end; on_chunk returning False stops the sweep at that chunk with the
    group's carry saved, and the resumed group starts from that carry and writes the uninterrupted sweep.csv."""
    from jaxrobo.training import driver
    from jaxrobo.training import train as training
    from jaxrobo.training.callbacks import Callback

    train, calls = training.train, []

    def spy(*args, **kwargs):
        calls.append(kwargs.get("population"))
        return train(*args, **kwargs)

    monkeypatch.setattr(training, "train", spy)

    class Recorder(Callback):
        def __init__(self, stop_at=None):
            self.events, self.stop_at = [], stop_at

        def on_training_start(self, trainer, initial):
            steps = None if initial is None else int(np.asarray(initial.env_steps, np.int64).sum())
            self.events.append(("start", trainer.config.number_splits, steps))

        def on_chunk(self, progress):
            self.events.append(("chunk", progress.chunks_done))
            return progress.chunks_done != self.stop_at

        def on_training_end(self, result):
            self.events.append(("end", type(result).__name__, result.stopped, result.chunks_done))

    state = str(tmp_path / "state")
    os.makedirs(state)
    plan = _plan()
    stopper = Recorder(stop_at=2)
    with pytest.raises(sweep.SweepInterrupted) as info:
        sweep.run_plan(plan, state_dir=state, callbacks=stopper)
    assert info.value.partial == (0, 2, 9) and os.path.exists(sweep_state.group_carry_path(state, 0))
    assert stopper.events == [("start", 4, None), ("chunk", 1), ("chunk", 2), ("end", "PopulationResult", True, 2)]
    assert len(calls) == 1 and isinstance(calls[0], driver.Population) and calls[0].n_rows == 4

    calls.clear()
    heard = Recorder()
    result = sweep.run_plan(plan, state_dir=state, callbacks=[heard])
    assert [type(p) for p in calls] == [driver.Population] * 2  # both groups, each one train()
    starts = [e for e in heard.events if e[0] == "start"]
    assert starts[0][:2] == ("start", 4) and starts[0][2] > 0 and starts[1] == ("start", 6, None)
    group_1 = heard.events[:heard.events.index(starts[1])]
    assert group_1[1] == ("chunk", 3) and group_1[-1] == ("end", "PopulationResult", False, 9)
    sweep.write_csv(result, str(tmp_path / "resumed.csv"))
    with open(tmp_path / "resumed.csv") as f:
        assert f.read() == _outputs(uninterrupted)[0]
