"""A run directory belongs to its user: jaxrobo replaces only the entries it owns (:data:`jaxrobo.io.rundir.OWNED`),
keeps every other file and folder through a resume, an ``--overwrite`` and a sweep, refuses to replace a directory
that is not a run, keeps an old run whole until a complete one replaces it (also when the new one is stopped),
reads only regular files and never writes through a symlink. Hostile cases of each class: exit 2, one line naming
what is wrong, nothing lost, nothing written outside the run. CPU-sized: the tiny cart-pole of tests/test_resume.py.
"""
from __future__ import annotations

import filecmp
import re
import os
import shutil
import signal

import pytest

from jaxrobo.cli import main
from jaxrobo.io import rundir
from jaxrobo.training import checkpoint

from stop_at_save import after_groups, signal_after_save
from test_resume import CLI_TINY

USER_FILES = {"notes.txt": "my notes", "analysis/fit.py": "print('mine')", "analysis/data/results.dat": "1 2 3"}


def _add_user_files(run) -> None:
    for rel, text in USER_FILES.items():
        path = os.path.join(run, rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)


def _user_files_kept(run) -> bool:
    for rel, text in USER_FILES.items():
        path = os.path.join(run, rel)
        if not os.path.isfile(path) or open(path).read() != text:
            return False
    return True


def _hidden(parent) -> list[str]:
    return sorted(n for n in os.listdir(parent) if n.startswith("."))


def _snapshot(run) -> dict[str, bytes]:
    out = {}
    for root, _, files in os.walk(run):
        for name in files:
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                out[os.path.relpath(path, run)] = f.read()
    return out


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A complete tiny run."""
    out = str(tmp_path_factory.mktemp("done") / "run")
    assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", out]) == 0
    return out


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """The tiny run stopped by SIGINT after its first checkpoint: an interrupted, resumable run."""
    out = str(tmp_path_factory.mktemp("stopped") / "run")
    with signal_after_save(checkpoint, signal.SIGINT):
        assert main(["train", *CLI_TINY, "--checkpoint-every", "1", "--out", out]) == 130
    assert rundir.is_resumable(out)
    return out


def _copy(src, tmp_path, name="run") -> str:
    dst = str(tmp_path / name)
    shutil.copytree(src, dst, symlinks=True)
    return dst


# ---- what jaxrobo owns -----------------------------------------------------------------------------------------
@pytest.mark.slow
def test_runs_and_sweeps_write_only_owned_names(done, stopped, tmp_path):
    """OWNED is derived from the writers: a complete run, an interrupted one and a sweep (with its heatmaps) write
    nothing it does not name."""
    from jaxrobo.training import sweep

    out = str(tmp_path / "sweep")
    args = ["--env", "CartPoleStayUp-v0", "--agent", "qlearn", "--grid", "alpha=0.1,0.5", "--grid",
            "gamma=0.9,0.99", "--seeds", "1", "--n-envs", "2", "--nepisodes", "2", "--nsteps", "20", "--set",
            "chunk_steps=10", "--set", "backend=analytic", "--set", "bins=null", "--eval-episodes", "1", "--out", out]
    assert sweep.main(args) == 0
    assert any(n.endswith(".png") for n in os.listdir(out))
    for run in (done, stopped, out):
        names = os.listdir(run)
        assert names and rundir.user_entries(run) == [], (run, names)
    _add_user_files(out)  # and a sweep replaced by --overwrite keeps them
    assert sweep.main([*args, "--overwrite"]) == 0
    assert rundir.is_complete(out) and _user_files_kept(out) and _hidden(tmp_path) == []
    assert rundir.owned(".checkpoint.npz.x1y2.tmp") and not rundir.owned(".notes.txt.swp")
    assert not rundir.owned("notes.txt") and not rundir.owned("src")


# ---- user files are kept ---------------------------------------------------------------------------------------
def test_user_files_survive_an_overwrite(done, tmp_path):
    out = _copy(done, tmp_path)
    _add_user_files(out)
    assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", out, "--overwrite"]) == 0
    assert rundir.is_complete(out) and _user_files_kept(out) and _hidden(tmp_path) == []


def test_user_files_inside_an_owned_folder_survive_an_overwrite(done, tmp_path, capsys):
    """``best/`` is a deep run's name; in a tabular run's directory a user's ``best/`` keeps what the user put there
    (jaxrobo removes only its own files inside, and the folder only if that empties it), and a ``tensorboard/``
    keeps a user's notes beside jaxrobo's event files."""
    out = _copy(done, tmp_path)
    os.makedirs(os.path.join(out, "best"))
    for rel in ("best/mine.txt", "best/policy.json", "tensorboard/README.md"):
        with open(os.path.join(out, rel), "w") as f:
            f.write("mine")
    assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", out, "--overwrite"]) == 0
    assert open(os.path.join(out, "best", "mine.txt")).read() == "mine"  # the new run has no best/: it moved in
    # the new run has its own tensorboard/: the user's folder stays in the old run, kept beside it and named
    kept = [os.path.join(d, n) for d, _, names in os.walk(tmp_path) for n in names if n == "README.md"]
    assert len(kept) == 1 and ".old" in kept[0] or ".run." in kept[0], kept
    assert "tensorboard" in capsys.readouterr().err
    assert rundir.is_complete(out)
    with pytest.raises(FileNotFoundError):  # jaxrobo's name inside: removed with the old run
        open(os.path.join(out, "best", "policy.json"))
    scratch = tmp_path / "scratch"
    (scratch / "best").mkdir(parents=True)
    (scratch / "best" / "policy.npz").write_text("x")
    (scratch / "best" / ".policy.npz.ab12.tmp").write_text("x")
    (scratch / "tensorboard").mkdir()
    (scratch / "tensorboard" / "events.out.tfevents.1.vm").write_text("x")
    assert rundir.remove_run(str(scratch)) and not scratch.exists()  # only jaxrobo's entries: all gone


def test_user_files_survive_a_resume(stopped, tmp_path):
    out = _copy(stopped, tmp_path)
    _add_user_files(out)
    assert main(["train", "--resume", out, "--no-progress"]) == 0
    assert rundir.is_complete(out) and _user_files_kept(out) and _hidden(tmp_path) == []


def test_a_stopped_overwrite_keeps_the_old_run_whole_and_resume_replaces_it(done, tmp_path, capsys):
    """SIGINT during an --overwrite run: the old run stays byte for byte (summary.json included), the new one's
    state waits in a hidden sibling; ``--resume OUT`` goes on with the new run and replaces the old one only once
    complete, the user's files kept."""
    out = _copy(done, tmp_path)
    _add_user_files(out)
    before = _snapshot(out)
    with signal_after_save(checkpoint, signal.SIGINT):
        assert main(["train", *CLI_TINY, "--checkpoint-every", "1", "--out", out, "--overwrite"]) == 130
    err = capsys.readouterr().err
    assert f"to go on: jaxrobo train --resume {out}" in err and "Traceback" not in err
    assert _snapshot(out) == before
    (partial,) = _hidden(tmp_path)
    assert rundir.is_resumable(str(tmp_path / partial))
    assert main(["train", "--resume", out, "--no-progress"]) == 0
    assert rundir.is_complete(out) and rundir.read_status(out)["resumed_after_chunk"] == 1
    assert _user_files_kept(out) and _hidden(tmp_path) == []
    # the path the results were published at, not the hidden sibling the resumed run went on in
    assert capsys.readouterr().out.rstrip().splitlines()[-1] == f"results in {os.path.abspath(out)}"
    assert not filecmp.cmp(os.path.join(out, "status.json"), os.path.join(done, "status.json"), shallow=False)


def test_publish_keeps_user_entries_and_a_killed_swap_gives_them_back(tmp_path):
    """The library rule under the CLI: publish() moves the user's entries of the replaced run into the new one;
    an old run left in a staging sibling by a kill between the swap and that move gives them back to the run at
    the next lock."""
    out = tmp_path / "run"
    out.mkdir()
    rundir.write_status(str(out), rundir.COMPLETE)
    (out / "summary.json").write_text('{"old": 1}')
    _add_user_files(out)
    staged = rundir.staging(str(out))
    rundir.write_status(staged, rundir.COMPLETE)
    rundir.publish(staged, str(out), overwrite=True)
    assert _user_files_kept(out) and not (out / "summary.json").exists() and _hidden(tmp_path) == []

    killed = tmp_path / ".run.abcd1234.partial"  # the old run, swapped out, its user files not yet moved
    killed.mkdir()
    rundir.write_status(str(killed), rundir.COMPLETE)
    (killed / "diary.md").write_text("day 1")
    with rundir.locked(str(out)):
        pass
    assert (out / "diary.md").read_text() == "day 1" and _hidden(tmp_path) == []


# ---- hostile cases: exit 2, one line, nothing lost, nothing written outside ------------------------------------
def _refused(argv, capsys, *fragments) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("project", [
    {"src/main.py": "print(1)", "README.md": "# mine", "results.dat": "1"},
    {"config.yaml": "lr: 0.1\n", "src/main.py": "print(1)", "README.md": "# mine"},  # one marker alone
    {"summary.json": "{}", "notes.txt": "x"},
])
def test_overwrite_of_a_directory_that_is_not_a_run_is_refused(project, tmp_path, capsys):
    home = tmp_path / "project"
    for rel, text in project.items():
        (home / rel).parent.mkdir(parents=True, exist_ok=True)
        (home / rel).write_text(text)
    before = _snapshot(home)
    _refused(["train", *CLI_TINY, "--out", str(home), "--overwrite"], capsys, str(home), "not a jaxrobo run")
    _refused(["sweep", "--env", "CartPoleStayUp-v0", "--grid", "alpha=0.1,0.5", "--out", str(home), "--overwrite"],
             capsys, str(home), "not a jaxrobo run")
    assert _snapshot(home) == before and _hidden(tmp_path) == []


def _outside(tmp_path, data: bytes = b"precious"):
    target = tmp_path / "elsewhere" / "precious.bin"
    target.parent.mkdir(exist_ok=True)
    target.write_bytes(data)
    return target


@pytest.mark.parametrize("name", ["episodes.csv", "records.npz", "tensorboard", "status.json", rundir.CHECKPOINT])
def test_resume_refuses_an_owned_entry_that_is_a_symlink(stopped, tmp_path, capsys, name):
    out = _copy(stopped, tmp_path)
    target = _outside(tmp_path) if name != "tensorboard" else tmp_path / "elsewhere"
    if name == "tensorboard":
        target.mkdir()
    if name in (rundir.CHECKPOINT, "status.json"):  # the link points at the real file, moved outside
        shutil.move(os.path.join(out, name), str(tmp_path / "elsewhere" / name))
        target = tmp_path / "elsewhere" / name
    else:
        p = os.path.join(out, name)
        shutil.rmtree(p) if os.path.isdir(p) else os.path.exists(p) and os.remove(p)
    os.symlink(target, os.path.join(out, name))
    before = _snapshot(tmp_path / "elsewhere")
    _refused(["train", "--resume", out, "--no-progress"], capsys, os.path.join(out, name), "symlink")
    assert _snapshot(tmp_path / "elsewhere") == before


@pytest.mark.parametrize("name", ["status.json", rundir.CHECKPOINT, "config.yaml"])
def test_resume_refuses_a_fifo_instead_of_hanging(stopped, tmp_path, capsys, name):
    out = _copy(stopped, tmp_path)
    os.remove(os.path.join(out, name))
    os.mkfifo(os.path.join(out, name))
    line = _refused(["train", "--resume", out, "--no-progress"], capsys)
    assert out in line


def test_a_checkpoint_linked_to_dev_zero_is_refused(stopped, tmp_path, capsys):
    out = _copy(stopped, tmp_path)
    os.remove(os.path.join(out, rundir.CHECKPOINT))
    os.symlink("/dev/zero", os.path.join(out, rundir.CHECKPOINT))
    _refused(["train", "--resume", out, "--no-progress"], capsys, "symlink")


def test_a_lock_file_that_is_a_symlink_is_not_written_through(tmp_path, capsys):
    target = _outside(tmp_path)
    os.symlink(target, tmp_path / ".run.lock")
    _refused(["train", *CLI_TINY, "--out", str(tmp_path / "run")], capsys, str(tmp_path / ".run.lock"), "symlink")
    assert target.read_bytes() == b"precious" and not (tmp_path / "run").exists()


@pytest.mark.parametrize("value, what", [("2024-01-01", "a date"), ("!!set {a: null}", "a set"),
                                         ("!!binary aGVsbG8=", "binary data")])
def test_resume_refuses_yaml_types_a_config_does_not_hold(stopped, tmp_path, capsys, value, what):
    out = _copy(stopped, tmp_path)
    with open(os.path.join(out, "config.yaml"), "a") as f:
        f.write(f"note: {value}\n")
    _refused(["train", "--resume", out, "--no-progress"], capsys, "config.yaml", what)
    assert rundir.is_resumable(out)


def test_export_into_the_run_itself_is_refused(done, tmp_path, capsys):
    run = _copy(done, tmp_path)
    before = _snapshot(run)
    _refused(["export", run, "--out", run, "--overwrite"], capsys, run, "run directory")
    assert _snapshot(run) == before
    assert main(["export", run, "--out", str(tmp_path / "policy")]) == 0


# ---- a stop during the evaluation keeps the finished training ------------------------------------------------------
def _sigint_in_the_evaluation(real):
    """``driver.evaluate_tables`` (``real``) with a SIGINT raised at its first segment, as a Ctrl-C there would."""
    def signalled(trainer, runner, key, env_params, progress=None, flights=None):
        def first_segment(p):
            signal.raise_signal(signal.SIGINT)
            progress(p)
        return real(trainer, runner, key, env_params, first_segment, flights)

    return signalled


def test_a_stop_during_the_evaluation_keeps_the_training_and_resume_only_evaluates(tmp_path, monkeypatch, capsys,
                                                                                  done):
    from jaxrobo.training import driver

    from test_resume import _assert_same_run, _counting_chunks

    signalled = _sigint_in_the_evaluation(driver.evaluate_tables)

    out = str(tmp_path / "run")
    with monkeypatch.context() as patch:
        patch.setattr(driver, "evaluate_tables", signalled)
        assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", out]) == 130
    err = capsys.readouterr().err
    assert "stopped during the evaluation: the finished training is kept" in err and "Traceback" not in err
    status = rundir.read_status(out)
    assert status["status"] == rundir.INTERRUPTED and status["episodes_done_min"] == status["nepisodes"]
    chunks_run = _counting_chunks(monkeypatch)
    assert main(["train", "--resume", out, "--no-progress"]) == 0
    assert chunks_run == [] and rundir.is_complete(out)
    _assert_same_run(out, done)


def _slow_closing_save(patch: pytest.MonkeyPatch, seconds: float = 1.0) -> list[str]:
    """The checkpoint after the last chunk takes ``seconds`` longer to write (it is written in a thread beside the
    evaluation: checkpoint.SaveInThread); returns a log of ``save`` and ``saved`` events."""
    import threading
    import time

    save, log = checkpoint.save_checkpoint, []

    def slow(*args, **kwargs):
        if threading.current_thread() is not threading.main_thread():
            log.append("save")
            time.sleep(seconds)
        out = save(*args, **kwargs)
        log.append("saved")
        return out

    patch.setattr(checkpoint, "save_checkpoint", slow)
    return log


def test_a_stop_while_the_closing_checkpoint_is_written_loses_nothing(tmp_path, monkeypatch, capsys, done):
    """SIGINT in the evaluation, the closing checkpoint still being written beside it: the run waits for it, is
    interrupted with it on disk, and the resume evaluates the same run without training."""
    from jaxrobo.training import driver

    from test_resume import _assert_same_run, _counting_chunks

    signalled = _sigint_in_the_evaluation(driver.evaluate_tables)

    out = str(tmp_path / "run")
    with monkeypatch.context() as patch:
        log = _slow_closing_save(patch)
        patch.setattr(driver, "evaluate_tables", signalled)
        assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", out]) == 130
    assert log == ["save", "saved"]
    assert rundir.read_status(out)["status"] == rundir.INTERRUPTED and rundir.is_resumable(out)
    chunks_run = _counting_chunks(monkeypatch)
    capsys.readouterr()
    assert main(["train", "--resume", out, "--no-progress"]) == 0, capsys.readouterr().err
    assert chunks_run == [] and rundir.is_complete(out)
    _assert_same_run(out, done)


def test_a_failed_evaluation_finds_the_closing_checkpoint_written(tmp_path, monkeypatch, capsys):
    """An error in the evaluation while the closing checkpoint is written: the error is the one raised, and the
    run directory holds the checkpoint, with the line saying how to go on."""
    from jaxrobo.training import driver

    def broken(*args, **kwargs):
        raise RuntimeError("the evaluation broke")

    out = str(tmp_path / "run")
    with monkeypatch.context() as patch:
        log = _slow_closing_save(patch)
        patch.setattr(driver, "evaluate_tables", broken)
        with pytest.raises(RuntimeError, match="the evaluation broke"):
            main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", out])
    assert log == ["save", "saved"] and rundir.is_resumable(out)
    assert "the run failed after saving its checkpoint" in capsys.readouterr().err


def test_save_in_thread_writes_the_last_save_beside_the_caller():
    """``last`` returns while its save runs; ``wait`` returns once it is written and raises its error once; a save
    on the way starts only after the one in flight."""
    import threading

    release, log = threading.Event(), []

    def save(carry, chunks):
        if carry == "slow":
            release.wait(10)
        if carry == "bad":
            raise OSError("disk full")
        log.append(chunks)

    saves = checkpoint.SaveInThread(save)
    saves.last("slow", 1)
    assert log == []
    threading.Timer(0.2, release.set).start()
    saves(None, 2)  # waits for the save in flight, then saves
    assert log == [1, 2] and saves.waited > 0
    saves.last("bad", 3)
    with pytest.raises(OSError, match="disk full"):
        saves.wait()
    saves.wait()  # raised once
    assert log == [1, 2]


# ---- environment variables, flags and keyword ranges: exit 2 / a ConfigError naming them ---------------------------
@pytest.mark.parametrize("var, value, fragment", [
    ("JAXROBO_PAUSE_BEFORE_PUBLISH", "soon", "JAXROBO_PAUSE_BEFORE_PUBLISH='soon'"),
    ("JAXROBO_PAUSE_BEFORE_PUBLISH", "nan", "expected a number of seconds"),
    ("JAXROBO_DISTRIBUTED", "yes", "JAXROBO_DISTRIBUTED='yes'"),
    ("JAXROBO_INIT_TIMEOUT", str(10**22), "JAXROBO_INIT_TIMEOUT="),
    ("JAXROBO_NUM_PROCESSES", "0", "JAXROBO_NUM_PROCESSES=0"),
    ("JAXROBO_PROCESS_ID", "-1", "JAXROBO_PROCESS_ID=-1"),
    ("JAXROBO_COORDINATOR", "nohost:x", "JAXROBO_COORDINATOR='nohost:x'"),
    ("JAXROBO_REUSE_TRACES", "sometimes", "JAXROBO_REUSE_TRACES='sometimes': expected on or off"),
])
def test_a_bad_jaxrobo_variable_is_refused_before_any_command(monkeypatch, capsys, tmp_path, var, value, fragment):
    monkeypatch.setenv(var, value)
    _refused(["export", str(tmp_path / "nothing"), "--out", str(tmp_path / "policy")], capsys, fragment)
    _refused(["list"], capsys, fragment)


def test_a_coordinator_port_in_use_is_refused_for_process_0(monkeypatch, capsys, tmp_path):
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        monkeypatch.setenv("JAXROBO_COORDINATOR", f"localhost:{port}")
        monkeypatch.setenv("JAXROBO_NUM_PROCESSES", "2")
        monkeypatch.setenv("JAXROBO_PROCESS_ID", "0")
        _refused(["list"], capsys, f"port {port} is already in use")


@pytest.mark.parametrize("var, value", [("JAX_ENABLE_X64", "maybe"), ("MUJOCO_GL", "bogus"), ("JAX_PLATFORMS", "tpu")])
def test_a_bad_third_party_variable_is_one_line_exit_2(var, value, tmp_path):
    """Read by JAX or MuJoCo at import (or at the first array): checked before, in a fresh process."""
    import subprocess
    import sys

    env = {**os.environ, var: value}
    proc = subprocess.run([sys.executable, "-m", "jaxrobo.cli", "export", str(tmp_path / "nothing"), "--out",
                           str(tmp_path / "policy")], env=env, capture_output=True, text=True, timeout=300,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    lines = [ln for ln in proc.stderr.strip().splitlines() if "warp" not in ln]  # MJX's optional-backend notes
    assert proc.returncode == 2 and len(lines) == 1 and f"{var}={value!r}" in lines[0], proc.stderr


def test_huge_integers_in_plot_and_eval_flags_are_refused(done, capsys, tmp_path):
    _refused(["plot", done, "--window", str(10**30), "--out", str(tmp_path / "a.png")], capsys, "--window")
    _refused(["eval", done, "--shift", "pole_mass=0.5,1", "--seed", str(10**20), "--out", str(tmp_path / "ev")],
             capsys, "--seed")


@pytest.mark.parametrize("env_id, kwargs, fragment", [
    ("QuadcopterGoto-v1", {"goal_min_dist": 6.0, "goal_max_dist": 2.0}, "goal_min_dist=6 is above goal_max_dist=2"),
    ("ArmReach-v0", {"elbow_min": 2.5, "elbow_max": 0.3}, "elbow_min=2.5 is above elbow_max=0.3"),
    ("CartPoleStayUp-v0", {"init_pos": 5.0}, "init_pos=5 is outside [min_base_pose_x, max_base_pose_x]"),
])
def test_make_and_gym_make_refuse_reversed_ranges_like_set(env_id, kwargs, fragment, capsys, tmp_path):
    import gymnasium as gym

    import jaxrobo
    from jaxrobo.core.config import ConfigError

    with pytest.raises(ConfigError, match=re.escape(fragment)):
        jaxrobo.make(env_id, **kwargs)
    with pytest.raises(ConfigError, match=re.escape(fragment)):
        gym.make(f"jaxrobo/{env_id}", **kwargs)
    sets = [a for k, v in kwargs.items() for a in ("--set", f"{k}={v}")]
    _refused(["train", "--env", env_id, *sets, "--out", str(tmp_path / "run")], capsys, fragment)
    assert not (tmp_path / "run").exists()


def test_a_sweep_point_with_a_start_off_the_track_is_refused_before_it_starts(capsys, tmp_path):
    _refused(["sweep", "--env", "CartPoleStayUp-v0", "--grid", "init_pos=0,3", "--out", str(tmp_path / "sw")],
             capsys, "init_pos=3 is outside")
    assert not (tmp_path / "sw").exists()


@pytest.mark.parametrize("seed", [-1, "3", 1.5, True, [0, -2], [0, "x"]])
def test_a_vector_reset_refuses_negative_or_string_seeds(seed):
    from jaxrobo.interop.gym_adapter import JaxroboVectorEnv

    env = JaxroboVectorEnv("CartPoleStayUp-v0", num_envs=2)
    with pytest.raises(ValueError, match="expected None or an integer >= 0"):
        env.reset(seed=seed)
    env.reset(seed=[1, None])  # what is allowed still is


@pytest.mark.parametrize("argv, flag", [(["train", "--env", ""], "--env"), (["train", "--out", ""], "--out"),
                                        (["train", "--preset", " "], "--preset"),
                                        (["sweep", "--env", "", "--grid", "alpha=0.1,0.2"], "--env")])
def test_an_empty_flag_is_refused_not_read_as_the_default(argv, flag, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _refused(argv, capsys, f"{flag} ", "empty")
    assert os.listdir(tmp_path) == []  # no training_results/ default run


def test_a_key_set_with_and_without_its_section_is_refused(capsys, tmp_path):
    _refused(["train", "--set", "alpha=0.3", "--set", "agent.alpha=0.4", "--out", str(tmp_path / "run")], capsys,
             "name the same key")


@pytest.mark.slow
def test_a_stopped_sweep_overwrite_keeps_the_old_sweep_and_resumes_from_its_name(tmp_path, capsys):
    """As for a run: the old sweep (and the user's files in it) stays whole; ``--resume OUT`` finds the new
    sweep's state beside it and replaces the old one once complete."""
    from jaxrobo.training.sweep import state as sweep_state

    from test_sweep_resume import ARGS, _main

    out = str(tmp_path / "sweep")
    assert _main([*ARGS, "--out", out]) == 0
    _add_user_files(out)
    before = _snapshot(out)
    with signal_after_save(sweep_state, signal.SIGINT, after_groups(1)):
        assert _main([*ARGS, "--out", out, "--overwrite"]) == 130
    assert _snapshot(out) == before and len(_hidden(tmp_path)) == 1
    capsys.readouterr()
    assert _main(["--resume", out]) == 0
    assert rundir.is_complete(out) and _user_files_kept(out) and _hidden(tmp_path) == []
    assert rundir.read_status(out)["status"] == rundir.COMPLETE


def test_a_lock_file_hard_linked_to_another_file_is_not_written(tmp_path, capsys):
    target = _outside(tmp_path)
    os.link(target, tmp_path / ".run.lock")
    _refused(["train", *CLI_TINY, "--out", str(tmp_path / "run")], capsys, str(tmp_path / ".run.lock"), "hard link")
    assert target.read_bytes() == b"precious"


def test_ctrl_c_in_a_command_without_its_own_handler_is_one_line_exit_130(monkeypatch, capsys, tmp_path):
    from jaxrobo import export

    def interrupted(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "export_run", interrupted)
    assert main(["export", str(tmp_path), "--out", str(tmp_path / "policy")]) == 130
    assert capsys.readouterr().err.strip() == "jaxrobo export: interrupted"


def test_eval_keeps_an_earlier_evaluation_unless_overwrite(done, capsys, tmp_path):
    """``jaxrobo eval --out DIR`` over a DIR with robustness.csv or robustness.png: refused before anything is read
    or flown (the user's file kept byte for byte); ``--overwrite`` replaces them."""
    out = tmp_path / "ev"
    out.mkdir()
    (out / "robustness.csv").write_text("mine")
    argv = ["eval", done, "--shift", "cart_mass=0.9", "--episodes", "2", "--tables", "1", "--out", str(out)]
    _refused(argv, capsys, f"--out {out}: holds robustness.csv already; give --overwrite to replace it")
    assert (out / "robustness.csv").read_text() == "mine" and os.listdir(out) == ["robustness.csv"]
    (out / "robustness.png").write_text("my figure")
    _refused(argv, capsys, "holds robustness.csv and robustness.png already; give --overwrite to replace them")
    assert main(argv + ["--overwrite"]) == 0
    assert (out / "robustness.csv").read_text().startswith("shift,value,metric")
    assert (out / "robustness.png").read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize("argv, fragment", [
    (["eval", "{run}", "--shift", "cart_mass=1", "--out", "{tmp}/afile/sub"], "--out {tmp}/afile/sub: {tmp}/afile"),
    (["eval", "{run}", "--shift", "cart_mass=1", "--out", "{tmp}/afile/a/b"], "--out {tmp}/afile/a/b: {tmp}/afile"),
    (["show", "{run}", "--video", "{tmp}/afile/v.gif"], "--video {tmp}/afile/v.gif: {tmp}/afile"),
    (["export", "{run}", "--out", "{tmp}/afile/x"], "--out {tmp}/afile/x: {tmp}/afile"),
    (["eval", "{run}", "--shift", "cart_mass=1", "--out", "{tmp}/dangling"], "--out {tmp}/dangling: {tmp}/dangling"),
    (["export", "{run}", "--out", "{tmp}/dangling/x"], "--out {tmp}/dangling/x: {tmp}/dangling is not a directory"),
])
def test_an_output_under_a_file_is_refused_before_any_work(done, capsys, tmp_path, monkeypatch, argv, fragment):
    """eval, show --video and export: an output path under a regular file (or a dangling link) is refused naming
    the flag and the path, exit 2, before anything is flown or exported (which failed at the first write)."""
    from jaxrobo import evaluate, export, show

    def forbidden(*_a, **_kw):
        raise AssertionError("the output path was not checked before the work")

    for module, name in ((evaluate, "evaluate"), (show, "video"), (export, "_check_run_dir")):
        monkeypatch.setattr(module, name, forbidden)
    (tmp_path / "afile").write_text("mine")
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling")
    sub = lambda a: a.replace("{run}", done).replace("{tmp}", str(tmp_path))  # noqa: E731
    line = _refused([sub(a) for a in argv], capsys, sub(fragment))
    assert "is a file, not a directory" in line or "is not a directory" in line
    assert sorted(os.listdir(tmp_path)) == ["afile", "dangling"] and (tmp_path / "afile").read_text() == "mine"
