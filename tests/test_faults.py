"""Faults from outside a run: two writers, a killed publish, a full or read-only disk, a moved directory, a corrupt
or hostile checkpoint, a second signal while the main thread is stuck in C. Each leaves the run whole or
resumable, says so in one line, and never replaces or deletes what it was not asked to.

The tests that train use the analytic cart-pole with a few envs and episodes (seconds on a CPU); the rest run
no JAX computation at all.
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from jaxrobo.cli import main
from jaxrobo.core.config import ConfigError
from jaxrobo.io import rundir
from stop_at_save import after_chunk, after_groups, signal_after_save

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": ROOT}
CP = "CartPoleStayUp-v0"
TINY = ["--env", CP, "--n-envs", "2", "--nepisodes", "4", "--set", "nsteps=20", "--set", "chunk_steps=10",
        "--set", "backend=analytic", "--set", "eval_episodes=1", "--no-progress"]


def _python(code: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], env={**ENV, **kw.pop("env", {})},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _holder(path: str) -> subprocess.Popen:
    """Another process that holds the run at ``path`` (as a running ``jaxrobo train`` does) until killed."""
    p = _python(f"""
        import sys, time
        from jaxrobo.io import rundir
        with rundir.locked({path!r}):
            print("locked", flush=True)
            time.sleep(120)
    """)
    assert p.stdout.readline().strip() == "locked", p.stderr.read()
    return p


# ---- two writers -------------------------------------------------------------------------------------------------
def test_a_second_writer_is_refused_with_the_first_ones_pid(tmp_path, capsys):
    out = str(tmp_path / "run")
    first = _holder(out)
    try:
        for argv in (["train", *TINY, "--out", out], ["sweep", "--n-envs", "2", "--nepisodes", "2", "--seeds", "1",
                                                      "--out", out]):
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert f"(pid {first.pid}) is writing this run directory" in err and "Traceback" not in err
        # its staging sibling (where an --overwrite run keeps its state) is the same run
        with pytest.raises(rundir.RunLocked, match=f"pid {first.pid}"):
            with rundir.locked(str(tmp_path / ".run.abcd1234.partial")):
                pass
    finally:
        first.kill()
        first.wait()
    assert not os.path.exists(out)  # nothing written by the refused writers


@pytest.mark.parametrize("state", ["new", "overwrite"])
def test_resume_of_a_run_another_process_writes_names_its_pid(state, tmp_path, capsys):
    """``--resume DIR`` while another process writes DIR, before its first checkpoint (a new run: no checkpoint;
    an --overwrite run: the complete old run, the new state not yet resumable): refused naming that process's pid,
    as ``--out DIR --overwrite`` is, not 'nothing to resume'; once it is gone, the old answer."""
    out = str(tmp_path / "lk")
    os.makedirs(out)
    with open(os.path.join(out, "config.yaml"), "w") as f:
        f.write(f"env_id: {CP}\n")
    rundir.write_status(out, rundir.RUNNING if state == "new" else rundir.COMPLETE)
    if state == "overwrite":
        with open(os.path.join(out, "summary.json"), "w") as f:
            f.write("{}")
    first = _holder(out)
    if state == "overwrite":  # the new run's state, before its first checkpoint (made once the lock is held)
        os.makedirs(str(tmp_path / ".lk.abcd1234.partial"))
    try:
        for argv, flag in ((["train", "--resume", out], "--resume"), (["train", *TINY, "--out", out, "--overwrite"],
                                                                      "--out")):
            assert main(argv) == 2
            err = capsys.readouterr().err
            assert err.startswith(f"jaxrobo train: {flag} {out}: another jaxrobo process (pid {first.pid}) is writing "
                                  "this run directory") and len(err.splitlines()) == 1, err
    finally:
        first.kill()
        first.wait()
    assert main(["train", "--resume", out]) == 2
    assert "nothing to resume" in capsys.readouterr().err


def test_a_lock_left_by_a_killed_process_is_taken_over(tmp_path):
    out = str(tmp_path / "run")
    first = _holder(out)
    first.send_signal(signal.SIGKILL)
    first.wait()
    assert os.path.exists(rundir.lock_path(out))  # the file stays; the kernel dropped the lock
    with rundir.locked(out):
        assert open(rundir.lock_path(out)).read().strip() == str(os.getpid())
    assert not os.path.exists(rundir.lock_path(out))


@pytest.mark.slow
def test_two_trainings_at_once_one_wins_the_other_is_refused(tmp_path):
    """Two real ``jaxrobo train`` processes on one --out: exactly one writes the run, the other exits 2."""
    out = str(tmp_path / "run")
    cmd = [sys.executable, "-m", "jaxrobo.cli", "train", *TINY, "--out", out]
    procs = [subprocess.Popen(cmd, env={**ENV, "JAXROBO_CACHE_DIR": str(tmp_path / "cache")},
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    refused = [err for code, err in results if code == 2]
    # Either the second found the lock (pid named) or, started after the first had finished, a complete run.
    assert codes == [0, 2], results
    assert "is writing this run directory" in refused[0] or "directory is not empty" in refused[0], refused
    assert rundir.is_complete(out)


# ---- kill -9 while publishing ---------------------------------------------------------------------------------
def test_kill_9_during_publish_leaves_a_partial_that_the_next_run_removes(tmp_path):
    out = str(tmp_path / "run")
    code = f"""
        import os
        from jaxrobo.io import rundir
        out = {out!r}
        with rundir.locked(out):
            live = rundir.live_dir(out)
            rundir.write_status(live, rundir.RUNNING)
            def write(staged):
                open(os.path.join(staged, "summary.json"), "w").write("{{}}")
                rundir.write_status(staged, rundir.COMPLETE)
            rundir.publish_results(out, live, write)
    """
    p = _python(code, env={rundir.PAUSE_ENV: "60"})
    deadline = time.time() + 60
    partials = []
    while time.time() < deadline and not partials:
        partials = [n for n in os.listdir(tmp_path) if n.startswith(".run.") and n.endswith(".partial")
                    and rundir.is_complete(os.path.join(tmp_path, n))]
        time.sleep(0.05)
    assert partials, p.stderr.read() if p.poll() is not None else "no staging directory appeared"
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert os.path.isdir(tmp_path / partials[0])  # left behind by the kill
    with rundir.locked(out):  # the next run on that --out
        pass
    assert not [n for n in os.listdir(tmp_path) if n.endswith(".partial")]
    assert rundir.read_status(out)["status"] == rundir.RUNNING  # the run's own state untouched


def test_a_partial_with_resumable_state_is_kept(tmp_path):
    """The hidden state directory of an interrupted --overwrite run is not litter: it stays."""
    keep = tmp_path / ".run.abcd1234.partial"
    keep.mkdir()
    (keep / rundir.CHECKPOINT).write_bytes(b"x")
    rundir.write_status(str(keep), rundir.INTERRUPTED)
    with rundir.locked(str(tmp_path / "run")):
        pass
    assert keep.is_dir()


# ---- --out that is a symlink, too long, unwritable ------------------------------------------------------------
def test_out_through_a_symlink_to_an_empty_folder_publishes_into_its_target(tmp_path):
    target = tmp_path / "target"
    target.mkdir()
    link = tmp_path / "link"
    link.symlink_to(target)
    assert rundir.check_out(str(link)) == str(target)
    live = rundir.live_dir(str(target))
    rundir.publish_results(str(target), live, lambda d: rundir.write_status(d, rundir.COMPLETE))
    assert link.is_symlink() and rundir.is_complete(str(link))
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]


@pytest.mark.parametrize("make, fragment", [
    (lambda t: (t / "loop").symlink_to(t / "loop"), "a symlink loop"),
    (lambda t: (t / "loop").symlink_to(t / "other") or (t / "other").symlink_to(t / "loop"), "a symlink loop"),
    (lambda t: (t / "loop").symlink_to(t / "nowhere"), "is a dangling symlink"),
    (lambda t: ((t / "f").write_text("x"), (t / "loop").symlink_to(t / "f")), "which is not a directory"),
])
def test_bad_symlinks_as_out_are_refused(tmp_path, make, fragment):
    make(tmp_path)
    with pytest.raises(ConfigError, match=fragment):
        rundir.check_out(str(tmp_path / "loop"))


def test_read_only_target_is_refused_before_anything_runs(tmp_path, monkeypatch):
    """As root os.access says yes to everything: the check tries a directory there (faked EROFS)."""
    import tempfile

    def erofs(*_a, **_kw):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkdtemp", erofs)
    with pytest.raises(ConfigError, match="Read-only file system"):
        rundir.check_out(str(tmp_path / "run"))


# ---- a full disk -----------------------------------------------------------------------------------------------
def _enospc(*_a, **_kw):
    raise OSError(errno.ENOSPC, "No space left on device", "/full/disk")


def test_plot_on_a_full_disk_fails_in_one_line_and_leaves_no_png(tmp_path, monkeypatch, capsys):
    import matplotlib.figure

    run = tmp_path / "r"
    run.mkdir()
    (run / "episode_stats.csv").write_text(
        "episode,return_mean,return_std,return_p10,return_p50,return_p90,length_mean,length_std,length_p10,"
        "length_p50,length_p90,epsilon\n0,1,0,1,1,1,5,0,5,5,5,0.1\n1,2,0,1,2,3,6,0,5,6,7,0.1\n")
    real = matplotlib.figure.Figure.savefig

    def half_then_full(self, f, **kw):  # writes some bytes, then the disk is full
        f.write(b"\x89PNG")
        _enospc()

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", half_then_full)
    assert main(["plot", str(run), "--out", str(tmp_path / "p.png")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "No space left on device" in err and "Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == ["r"]  # no 0-byte or torn PNG, no temporary file
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", real)


def test_train_on_a_full_disk_before_its_first_checkpoint_leaves_nothing(tmp_path, monkeypatch, capsys):
    from jaxrobo.io import results

    monkeypatch.setattr(results, "write_config", _enospc)
    out = tmp_path / "run"
    assert main(["train", *TINY, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "No space left on device" in err and "nothing was kept" in err and "Traceback" not in err
    assert not out.exists() and os.listdir(tmp_path) == []


# ---- a moved run directory or sweep ----------------------------------------------------------------------------
def _interrupted_run(out, extra=()):
    """A tiny ``jaxrobo train`` stopped by SIGTERM after its first checkpoint (exit 143, resumable)."""
    from jaxrobo.training import checkpoint

    with signal_after_save(checkpoint, signal.SIGTERM, after_chunk(1)):
        assert main(["train", *TINY, "--checkpoint-every", "1", *extra, "--out", str(out)]) == 143


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("interrupted") / "run"
    _interrupted_run(out)
    return out


@pytest.mark.slow
def test_a_moved_run_resumes_where_it_is_and_keeps_checkpoint_every(interrupted, tmp_path, monkeypatch, capsys):
    from jaxrobo.training import checkpoint

    a, b = tmp_path / "a", tmp_path / "b"
    shutil.copytree(interrupted, a)
    assert rundir.read_status(str(a))["checkpoint_every"] == 1
    shutil.move(str(a), str(b))
    a.mkdir()  # an unrelated directory now at the old place
    (a / "mine.txt").write_text("not a run")
    saves = []
    real = checkpoint.save_checkpoint
    monkeypatch.setattr(checkpoint, "save_checkpoint", lambda *a, **kw: (saves.append(a[2]), real(*a, **kw))[1])
    assert main(["train", "--resume", str(b), "--no-progress"]) == 0
    assert rundir.is_complete(str(b)) and sorted(os.listdir(a)) == ["mine.txt"]
    # --checkpoint-every 1 came back from status.json: a save after every chunk (the default saves by time)
    assert sorted(set(saves)) == list(range(2, max(saves) + 1)) and len(set(saves)) > 2
    summary = json.loads((b / "summary.json").read_text())
    assert 0 < summary["restored_env_steps"] < summary["env_steps"]
    # The rate counts this process's steps only (not the restored ones). The summary rounds run_seconds to 1 ms and
    # the rate to 0.1, so the check allows exactly that rounding (a run of a few tens of ms moves the quotient of
    # the rounded figures by more than 1 %).
    rate, secs, steps = (summary[k] for k in ("env_steps_per_second", "run_seconds", "env_steps_this_process"))
    assert steps / (secs + 5e-4) - 0.05 <= rate <= steps / max(secs - 5e-4, 1e-9) + 0.05


@pytest.mark.slow
def test_a_moved_sweep_resumes_where_it_is_and_touches_nothing_else(tmp_path, capsys):
    from jaxrobo.training import sweep
    from jaxrobo.training.sweep import state as sweep_state

    args = ["--env", CP, "--grid", "number_splits=4,6", "--seeds", "1", "--n-envs", "2", "--nepisodes", "2",
            "--nsteps", "20", "--set", "chunk_steps=10", "--set", "backend=analytic", "--set", "bins=null",
            "--eval-episodes", "1", "--no-plots"]
    a, b = tmp_path / "a", tmp_path / "b"
    with signal_after_save(sweep_state, signal.SIGTERM, after_groups(1)):
        assert sweep.main([*args, "--out", str(a)]) == 143
    shutil.move(str(a), str(b))
    a.mkdir()  # an unrelated complete run now where the sweep was
    rundir.write_status(str(a), rundir.COMPLETE)
    (a / "summary.json").write_text("{}")
    before = sorted(os.listdir(a))
    capsys.readouterr()
    assert sweep.main(["--resume", str(b)]) == 0
    assert sorted(os.listdir(a)) == before and json.loads((a / "summary.json").read_text()) == {}
    assert rundir.is_complete(str(b)) and (b / "sweep.csv").is_file()


def test_resume_out_is_derived_from_the_directory_never_from_a_recorded_path(tmp_path):
    assert rundir.run_name(str(tmp_path / "b")) == str(tmp_path / "b")
    assert rundir.run_name(str(tmp_path / ".b.x1y2z3w4.partial")) == str(tmp_path / "b")


# ---- a corrupt or hostile checkpoint ---------------------------------------------------------------------------
def _flip(path, at):
    data = bytearray(open(path, "rb").read())
    data[at] ^= 0xFF
    open(path, "wb").write(bytes(data))


def _huge_header(path):
    """Rewrite leaf_0's .npy header to claim 2^40 more rows (the data stays as it was; the zip's CRC is right)."""
    import zipfile

    with zipfile.ZipFile(path) as z:
        members = {i.filename: z.read(i) for i in z.infolist()}
    raw = members["leaf_0.npy"]
    assert raw[6:8] == b"\x01\x00"  # format 1.0: a 2-byte header length
    hlen = int.from_bytes(raw[8:10], "little")
    header = raw[10:10 + hlen].decode("latin1").strip()
    header = header.replace("'shape': (", "'shape': (1099511627776, ")
    header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
    forged = raw[:8] + len(header).to_bytes(2, "little") + header.encode("latin1") + raw[10 + hlen:]
    with zipfile.ZipFile(path, "w") as z:
        for name, blob in members.items():
            z.writestr(name, forged if name == "leaf_0.npy" else blob)


def _tables_file(path):
    """The file of the checkpoint's tables, beside it (:func:`jaxrobo.training.checkpoint.save_checkpoint`)."""
    with np.load(path, allow_pickle=False) as z:
        return os.path.join(os.path.dirname(path), str(z["tables_file"]))


def _rewrite(path, change):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(change(arrays))
    np.savez(path, **arrays)


def _nan_tables(path):
    _rewrite(_tables_file(path), lambda a: {"q": np.full_like(a["q"], np.nan)})


def _other_tables(path):
    """The tables file holds other tables (a valid file, under the name the checkpoint records)."""
    _rewrite(_tables_file(path), lambda a: {"q": a["q"] + 1})


def _records_file(path):
    """The file of the checkpoint's episode records, beside it (:func:`jaxrobo.training.checkpoint.save_checkpoint`)."""
    with np.load(path, allow_pickle=False) as z:
        return os.path.join(os.path.dirname(path), str(z["records_file"]))


def _records(change):
    """Rewrite the checkpoint's records file with its first episode-record member (``returns``) changed by
    ``change(name, array)`` (a new ``{name: array}``; empty drops it), and the checkpoint with the CRC-32s of the
    new file's members (a forged pair: the loader's own checks of the records must refuse it)."""
    import zipfile

    def corrupt(path):
        where = _records_file(path)
        with np.load(where, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays.update(change("returns", arrays.pop("returns")))
        np.savez(where, **arrays)
        with zipfile.ZipFile(where) as zf:
            crcs = [zf.getinfo(f"{n}.npy").CRC if f"{n}.npy" in zf.namelist() else 0
                    for n in ("returns", "lengths", "terminated")]
        _rewrite(path, lambda a: {"records_crc": np.array(crcs, np.int64)})
    return corrupt


def _negative_counts(path):
    """Every int32 vector of the carry (the envs' counters, the episode count among them) made negative."""
    _rewrite(path, lambda a: {k: -x - 1 for k, x in a.items()
                              if k.startswith("leaf_") and x.dtype == np.int32 and x.ndim == 1})


def _deflate_damaged(path):
    """A byte in the middle of the tables file's deflated ``q`` flipped: zipfile's inflate fails (the standard
    library's zlib.error) or its CRC does."""
    import zipfile

    where = _tables_file(path)
    with zipfile.ZipFile(where) as zf:
        info = zf.getinfo("q.npy")
    assert info.compress_type == zipfile.ZIP_DEFLATED
    with open(where, "rb") as f:
        f.seek(info.header_offset + 26)
        start = info.header_offset + 30 + sum(int.from_bytes(f.read(2), "little") for _ in range(2))
    _flip(where, start + info.compress_size // 2)


@pytest.mark.parametrize("corrupt, fragment", [
    (lambda p: _rewrite(p, lambda a: {"chunks_done": np.int64(10**6)}), "chunks_done=1000000 is outside 0.."),
    (lambda p: _rewrite(p, lambda a: {"chunks_done": np.int64(-1)}), "chunks_done=-1 is outside 0.."),
    (_negative_counts, "holds negative counts"),
    (lambda p: _rewrite(p, lambda a: {"fingerprint": np.array("[" * 100_000 + "]" * 100_000)}),
     "not a jaxrobo checkpoint (JSON nested too deeply)"),
    (_deflate_damaged, "cannot be read as plain arrays"),
    (_records(lambda n, x: {n: np.zeros((x.shape[0], 10_000), x.dtype)}), "with at most"),
    (_records(lambda n, x: {n: x.astype(np.float64)}), "float64"),
    (_records(lambda n, x: {}), "cannot be matched to it"),
    (lambda p: _rewrite(_records_file(p), lambda a: {"lengths": np.ones((len(a["lengths"]), 1), np.int32)}),
     "holds other records than the checkpoint recorded"),
    (lambda p: os.remove(_records_file(p)), "(checkpoint.records."),
    (lambda p: _rewrite(p, lambda a: {"records_file": np.array("../records.npz")}), "not a checkpoint's records file"),
    (lambda p: open(p, "r+b").truncate(os.path.getsize(p) // 2), "cannot be read as plain arrays"),
    (lambda p: open(p, "r+b").truncate(10), "cannot be read as plain arrays"),
    (lambda p: _flip(p, os.path.getsize(p) // 3), "the checkpoint"),
    (lambda p: open(p, "wb").write(b"not a zip"), "cannot be read as plain arrays"),
    (_huge_header, "claims shape (1099511627776"),
    (_nan_tables, "non-finite values (NaN or inf)"),
    (_other_tables, "holds other tables than the checkpoint recorded"),
    (lambda p: os.remove(_tables_file(p)), "are missing beside it"),
    (lambda p: _rewrite(p, lambda a: {"tables_file": np.array("../qtables.npz")}), "not a checkpoint's tables file"),
    (lambda p: _rewrite(p, lambda a: {"tables_file": np.array(["a", "b"])}), "not a checkpoint's tables file"),
    (lambda p: _rewrite(_tables_file(p), lambda a: {"q": a["q"][:1]}), "expected"),
])
def test_a_corrupt_checkpoint_is_refused_in_one_line(interrupted, tmp_path, capsys, corrupt, fragment):
    out = tmp_path / "run"
    shutil.copytree(interrupted, out)
    corrupt(str(out / rundir.CHECKPOINT))
    before = {n: (out / n).read_bytes() for n in os.listdir(out) if (out / n).is_file()}
    assert main(["train", "--resume", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err and err.count("\n") == 1, err
    assert {n: (out / n).read_bytes() for n in os.listdir(out) if (out / n).is_file()} == before


def test_npz_headers_are_checked_before_any_data_is_read(tmp_path):
    from jaxrobo.io.npz import NpzError, read_npz

    path = str(tmp_path / "a.npz")
    np.savez(path, q=np.zeros((2, 3), np.float32), n=np.int64(3))
    assert read_npz(path, expect={"q": ((2, 3), np.float32)})["q"].shape == (2, 3)
    with pytest.raises(NpzError, match=r"array 'q' is \(2, 3\) float32, expected \(2, 4\) float32"):
        read_npz(path, expect={"q": ((2, 4), np.float32)})
    with pytest.raises(NpzError, match="array 'q' is .* expected .* float64"):
        read_npz(path, expect={"q": ((2, 3), np.float64)})
    with pytest.raises(NpzError, match="no array 'r'"):
        read_npz(path, expect={"r": ((1,), np.float32)})
    with pytest.raises(NpzError, match="limit 8"):
        read_npz(path, max_bytes=8)


def test_a_damaged_deflate_stream_is_refused_as_npz_error(tmp_path):
    """zipfile inflates with the standard library's zlib, whose error class is not zlib-ng's: every byte of a
    member's deflate stream flipped in turn is refused as an NpzError (never a zlib.error)."""
    import zipfile

    from jaxrobo.io.npz import NpzError, read_npz

    path = str(tmp_path / "a.npz")
    np.savez_compressed(path, q=np.arange(4096, dtype=np.float32) % 7)
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("q.npy")
    raw = open(path, "rb").read()
    local = info.header_offset  # the data starts after the local header, its name and its (zip64) extra field
    start = local + 30 + int.from_bytes(raw[local + 26:local + 28], "little") + int.from_bytes(
        raw[local + 28:local + 30], "little")
    kinds = set()
    for at in range(start, start + info.compress_size - 4):  # not the last bits, which may be padding
        _flip(path, at)
        with pytest.raises(NpzError) as err:  # the .npy header's bytes or the data's
            read_npz(path)
        kinds.add(str(err.value).split("(")[-1].split(":")[0])
        open(path, "wb").write(raw)
    assert "error" in kinds, kinds  # the inflate's own error among them, not only CRC mismatches


def test_only_the_tables_members_are_read_from_qtables(tmp_path):
    """A member ``qtables.npz`` has no use for is neither checked nor inflated (a few KB of file could claim GBs)."""
    import zipfile

    from jaxrobo.io.results import load_tables

    np.savez_compressed(tmp_path / "qtables.npz", q=np.zeros((1, 1, 4, 2), np.float32), low=np.zeros(2),
                        edges_0=np.arange(3.0))
    with zipfile.ZipFile(tmp_path / "qtables.npz", "a", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("junk.npy", b"\x93NUMPY" + b"not a header at all")
    assert sorted(load_tables(str(tmp_path))) == ["edges_0", "low", "q"]


def test_json_read_back_nested_past_the_recursion_limit_is_malformed_json(tmp_path):
    from jaxrobo.core.config import parse_json
    from jaxrobo.io.results import selected_table

    nested = "[" * 100_000 + "]" * 100_000
    with pytest.raises(ValueError, match="nested too deeply"):
        parse_json(nested)
    (tmp_path / rundir.STATUS).write_text(nested)
    assert rundir.read_status(str(tmp_path)) is None
    (tmp_path / rundir.STATUS).write_text(json.dumps({"status": "complete", "pad": " " * rundir.STATUS_MAX_BYTES}))
    assert rundir.read_status(str(tmp_path)) is None  # past the cap: not one of jaxrobo's statuses
    (tmp_path / "summary.json").write_text(nested)
    assert selected_table(str(tmp_path), 4) == 0


# ---- a second signal while the main thread is stuck in C ---------------------------------------------------------
@pytest.mark.parametrize("second", ["default", "exit"])
def test_sigterm_twice_ends_a_process_stuck_in_c(second):
    """The main thread blocked in a C call (as in an XLA compile or a device wait) runs no Python handler: the
    second SIGTERM still ends the process within the grace period, not when the call returns (30 s)."""
    # "ready" comes from a shell that system(3) starts, so the main thread is already inside the C call when the
    # signals arrive (printing it from Python left a window in which, on a loaded machine, the Python handler
    # ran before the call and the second signal met the default action). The shell execs a 15 s sleep with its
    # output closed, so the orphan left behind holds none of our pipes.
    p = _python(f"""
        import ctypes, signal
        from jaxrobo.training.driver import StopOnSignal
        system = ctypes.CDLL(None).system
        with StopOnSignal(second={second!r}):
            signal.pthread_sigmask(signal.SIG_BLOCK, {{signal.SIGTERM, signal.SIGINT}})
            system(b"echo ready; exec sleep 15 </dev/null >/dev/null 2>&1")
    """)
    assert p.stdout.readline().strip() == "ready"
    t0 = time.time()
    p.send_signal(signal.SIGTERM)
    time.sleep(0.2)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=20)
    assert p.returncode == 128 + signal.SIGTERM and time.time() - t0 < 10
    assert "SIGTERM twice: quitting now" in err


# ---- the checked step ------------------------------------------------------------------------------------------
def test_checked_actions_raise_on_the_host_and_flag_under_jit():
    import jax
    import jax.numpy as jnp

    import jaxrobo
    from jaxrobo.task.wrappers import CheckedActions

    env = CheckedActions(jaxrobo.make(CP, backend="analytic"))
    state = env.reset(jax.random.key(0))
    assert not bool(state.info["invalid_action"])
    assert not bool(env.step(state, 1).info["invalid_action"])
    n = env.action_space().n
    for bad in (n, -1, float("nan"), 2.7, 1e9):
        with pytest.raises(ValueError, match=r"action=.* is not in the action space; expected an integer in 0\.\."):
            env.step(state, bad)
    step = jax.jit(env.step)
    flags = [bool(step(state, jnp.asarray(a)).info["invalid_action"]) for a in (0, n - 1, n, -1)]
    assert flags == [False, False, True, True]
    flags = [bool(step(state, jnp.asarray(a, jnp.float32)).info["invalid_action"]) for a in (1.0, 2.7, np.nan)]
    assert flags == [False, True, True]
    # a whole rollout keeps one carry structure
    final, _ = jax.lax.scan(lambda s, a: (step(s, a), None), state, jnp.asarray([0, 7, 1]))
    assert bool(final.info["invalid_action"]) is False  # the flag is per step: the last action was valid


# ---- a reader that goes away -------------------------------------------------------------------------------------
def test_a_closed_stdout_pipe_does_not_lose_the_run(tmp_path):
    """``jaxrobo train ... | head -1``: the reader leaves after one line; the command carries on and the run is
    written whole (a closed pipe used to end it with 'Broken pipe' and nothing kept)."""
    out = str(tmp_path / "run")
    p = subprocess.Popen([sys.executable, "-m", "jaxrobo.cli", "train", *TINY, "--out", out], env=ENV,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline()  # the header line, then the reader is gone
    p.stdout.close()
    err = p.stderr.read()
    assert p.wait(timeout=300) == 0, err
    assert "Broken pipe" not in err
    with open(os.path.join(out, "summary.json")) as f:
        assert json.load(f)["env_steps"] > 0
