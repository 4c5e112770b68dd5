"""Nothing lost: run directories checked before compiling, checkpoints of the whole carry, interrupt and resume
bit for bit, real signals, refused checkpoints."""
from __future__ import annotations

import filecmp
import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from jaxrobo.training import checkpoint as ckpt
from jaxrobo.io import rundir
from jaxrobo.training import train as training
from jaxrobo.cli import main
from jaxrobo.core.config import ConfigError
from jaxrobo.io.results import save_run
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: How the run was executed (timings, what a resume restored), not what it computed.
TIMING = {"compile_seconds", "run_seconds", "eval_seconds", "write_seconds", "env_steps_per_second", "startup_seconds",
          "target_check_seconds", "target_met_at_run_seconds", "checkpoint_seconds", "checkpoint_write_seconds",
          "restored_env_steps", "env_steps_this_process", "resumed_after_chunk"}
CARTPOLE = dict(n_envs=4, nepisodes=6, nsteps=40, chunk_steps=15, eval_episodes=2, eval_envs=2,
                bins=[3, 6, 8, 10], state_low=[-2.4, -1.0, -0.3, -2.0], state_high=[2.4, 1.0, 0.3, 2.0])
QUADCOPTER = dict(n_envs=4, nepisodes=6, nsteps=30, chunk_steps=10, eval_episodes=2, eval_envs=2)
CASES = {"CartPoleStayUp-v0": CARTPOLE, "QuadcopterGoto-v1": QUADCOPTER}


def _save(result, spec, out):
    save_run(str(out), result, spec.to_dict(), Trainer(spec.env, spec.config).disc)
    return str(out)


def _assert_same_run(a: str, b: str) -> None:
    """Two run directories hold the same results: CSVs byte for byte, arrays bit for bit, summary but timings."""
    for name in ("config.yaml", "episodes.csv", "episode_stats.csv", "eval.csv"):
        if os.path.exists(os.path.join(a, name)) or os.path.exists(os.path.join(b, name)):
            assert filecmp.cmp(os.path.join(a, name), os.path.join(b, name), shallow=False), name
    for name in ("records.npz", "qtables.npz"):
        with np.load(os.path.join(a, name), allow_pickle=False) as x, np.load(os.path.join(b, name),
                                                                             allow_pickle=False) as y:
            assert set(x) == set(y)
            for k in x:
                np.testing.assert_array_equal(x[k], y[k], err_msg=f"{name}:{k}")
    sa, sb = (json.load(open(os.path.join(d, "summary.json"))) for d in (a, b))
    assert {k: v for k, v in sa.items() if k not in TIMING} == {k: v for k, v in sb.items() if k not in TIMING}


@pytest.fixture(scope="module", params=list(CASES))
def uninterrupted(request, tmp_path_factory):
    spec = resolve(request.param, overrides=CASES[request.param])
    result = training.train(spec.env, spec.config, spec.agent_params)
    assert result.complete and result.chunks_done > 3
    return spec, result, _save(result, spec, tmp_path_factory.mktemp("full") / "run")


@pytest.mark.slow
@pytest.mark.parametrize("stop_at", [1, 3])
def test_interrupted_and_resumed_equals_uninterrupted(uninterrupted, stop_at, tmp_path):
    """Stopped after ``stop_at`` chunks (``should_stop`` asked before each chunk), saved, loaded and resumed: the
    tables, records, episodes.csv and summary equal those of the run that never stopped."""
    spec, full, full_dir = uninterrupted
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    fingerprint = ckpt.carry_fingerprint(template, spec.to_dict())
    path = str(tmp_path / rundir.CHECKPOINT)
    asked, saved = [], []

    def should_stop():
        asked.append(1)
        return len(asked) > stop_at

    def checkpoint(runner, chunks_done):
        ckpt.save_checkpoint(path, runner, chunks_done, fingerprint)
        saved.append(chunks_done)

    part = training.train(spec.env, spec.config, spec.agent_params, should_stop=should_stop, checkpoint=checkpoint)
    assert not part.complete and part.chunks_done == stop_at and saved == [stop_at]
    assert part.eval_lengths is None and np.all(part.episodes_done < spec.config.nepisodes)
    done = part.episodes_done[:, None] > np.arange(spec.config.nepisodes)
    np.testing.assert_array_equal(part.returns[done], full.returns[done])  # the finished episodes are final

    with np.load(path, allow_pickle=False) as data:  # plain arrays: no pickle needed to read it
        assert int(data["chunks_done"]) == stop_at
        # The episode records are kept up to their last written column (the loader pads the zeros back).
        widths = {data[k].shape[1] for k in data if k.startswith("records_")}
        assert len([k for k in data if k.startswith("records_")]) == 3
        assert max(widths) == part.episodes_done.max() < spec.config.nepisodes
    runner, chunks_done = ckpt.load_checkpoint(path, template, fingerprint)
    assert chunks_done == stop_at
    resumed = training.train(spec.env, spec.config, spec.agent_params, initial=runner, start_chunk=chunks_done)
    assert resumed.complete and resumed.chunks_done == full.chunks_done
    for field in ("q", "returns", "lengths", "terminated", "nan_episodes", "eval_returns", "eval_lengths"):
        np.testing.assert_array_equal(getattr(resumed, field), getattr(full, field), err_msg=field)
    _assert_same_run(_save(resumed, spec, tmp_path / "resumed"), full_dir)


def test_a_checkpoint_of_another_config_or_code_is_refused(uninterrupted, tmp_path):
    spec, _, _ = uninterrupted
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    fingerprint = ckpt.carry_fingerprint(template, spec.to_dict())
    path = str(tmp_path / rundir.CHECKPOINT)
    ckpt.save_checkpoint(path, jax.jit(trainer.init)(jax.random.key(0), spec.agent_params,
                                                         spec.env.default_params), 0, fingerprint)
    changed = json.loads(json.dumps(spec.to_dict()))
    changed["agent_params"]["alpha"] = 0.123
    with pytest.raises(ckpt.CheckpointError, match=r"agent_params.alpha: .* in the checkpoint vs 0.123 now"):
        ckpt.load_checkpoint(path, template, ckpt.carry_fingerprint(template, changed))
    with pytest.raises(ckpt.CheckpointError, match="source code"):
        ckpt.load_checkpoint(path, template, {**fingerprint, "sources": "0" * 64})
    with pytest.raises(ckpt.CheckpointError, match="JAX version"):
        ckpt.load_checkpoint(path, template, {**fingerprint, "jax": "0.0.1"})


@pytest.mark.parametrize("shared,tables_first", [(False, True), (True, True), (False, False)])
def test_the_checkpoints_tables_are_the_results_file_and_load_back(tmp_path, monkeypatch, shared, tables_first):
    """With ``tables=`` the carry's tables go to a file beside the checkpoint laid out as qtables.npz (what a
    finished run links as its results); a later checkpoint replaces that file, the carry loads back whole. The
    checkpoint names that file and its CRC in its last members, whichever copy starts first (an accelerator's
    order, the records' copies before the tables', taken here on the CPU)."""
    import zipfile

    from jaxrobo.io.results import discretiser_arrays, write_tables

    monkeypatch.setattr(ckpt, "tables_copy_first", lambda tables: tables_first)
    spec = resolve("CartPoleStayUp-v0", overrides={**CARTPOLE, "shared_table": shared})
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    fingerprint = ckpt.carry_fingerprint(template, spec.to_dict())
    runner = jax.jit(trainer.init)(jax.random.key(1), spec.agent_params, spec.env.default_params)
    runner = runner.replace(agent=runner.agent.replace(q=runner.agent.q + jax.random.uniform(
        jax.random.key(2), runner.agent.q.shape)))
    path = str(tmp_path / rundir.CHECKPOINT)
    extra = discretiser_arrays(trainer.disc)
    first = ckpt.save_checkpoint(path, runner, 1, fingerprint, tables=extra).tables
    second = ckpt.save_checkpoint(path, runner, 2, fingerprint, tables=extra).tables
    assert first != second and sorted(os.listdir(tmp_path)) == sorted([rundir.CHECKPOINT, os.path.basename(second)])
    assert all(rundir.owned(n) for n in os.listdir(tmp_path))
    with np.load(path, allow_pickle=False) as data:  # the tables are not in the checkpoint itself
        assert max(data[k].size for k in data.files if k.startswith("leaf_")) < runner.agent.q.size
        assert data.files[-2:] == ["tables_file", "tables_crc"] and str(data["tables_file"]) == os.path.basename(second)
    with zipfile.ZipFile(second) as zf:
        assert int(np.load(path)["tables_crc"]) == zf.getinfo("q.npy").CRC
    q = np.asarray(runner.agent.q)
    write_tables(str(tmp_path), q[None] if shared else q, trainer.disc)  # what save_run writes without a link
    with np.load(second, allow_pickle=False) as a, np.load(tmp_path / "qtables.npz", allow_pickle=False) as b:
        assert set(a.files) == set(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    loaded, chunks_done = ckpt.load_checkpoint(path, template, fingerprint)
    assert chunks_done == 2
    for x, y in zip(jax.tree.leaves(loaded), jax.tree.leaves(runner)):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("budget", ["episodes", "steps"])
def test_the_checkpoints_records_are_the_results_file_and_load_back(tmp_path, budget):
    """With ``epsilon=`` the carry's episode records go to a file beside the checkpoint laid out as records.npz
    (what a finished run links as its results; under a step budget with each env's count of recorded episodes),
    a later checkpoint replaces that file and the older one is removed, the carry loads back whole; a checkpoint
    whose records file holds other records is refused."""
    from jaxrobo.io.results import write_episodes
    from jaxrobo.tabular.learner import epsilon_schedule

    overrides = dict(CARTPOLE, n_envs=6, nepisodes=5, stop_at_target=False)
    if budget == "steps":
        overrides.update(total_steps=6 * 90)
    spec = resolve("CartPoleStayUp-v0", overrides=overrides)
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    fingerprint = ckpt.carry_fingerprint(template, spec.to_dict())
    path = str(tmp_path / rundir.CHECKPOINT)
    epsilon = epsilon_schedule(spec.agent_params, spec.config.nepisodes)
    carries = []
    result = training.train(spec.env, spec.config, spec.agent_params,
                            checkpoint=lambda runner, chunks: carries.append((jax.tree.map(jax.numpy.copy, runner),
                                                                              chunks)),
                            checkpoint_every=1)  # copies: the next chunk reuses the carry's buffers
    assert result.complete and len(carries) >= 2
    (earlier, n_earlier), (runner, chunks) = carries[-2], carries[-1]
    first = ckpt.save_checkpoint(path, earlier, n_earlier, fingerprint, epsilon=epsilon)
    second = ckpt.save_checkpoint(path, runner, chunks, fingerprint, epsilon=epsilon)
    assert first.records != second.records and first.tables is second.tables is None
    assert sorted(os.listdir(tmp_path)) == sorted([rundir.CHECKPOINT, os.path.basename(second.records)])
    assert all(rundir.owned(n) for n in os.listdir(tmp_path))
    with np.load(path, allow_pickle=False) as data:  # the records are not in the checkpoint itself
        assert not [k for k in data.files if k.startswith("records_") and k[8:].isdigit()]
        assert str(data["records_file"]) == os.path.basename(second.records) and data["records_crc"].shape == (3,)
    # What the results write from the finished run's records, without a link: the same arrays.
    write_episodes(str(tmp_path / "results"), result.returns, result.lengths, result.terminated, result.epsilon,
                   episodes_done=None if result.all_recorded() else result.episodes_done)
    assert (budget == "steps") == (not result.all_recorded())
    with np.load(second.records, allow_pickle=False) as a, \
            np.load(tmp_path / "results" / "records.npz", allow_pickle=False) as b:
        assert a.files == b.files == ["returns", "lengths", "terminated", "epsilon"] + \
            (["episodes_done"] if budget == "steps" else [])
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
            assert a[k].dtype == b[k].dtype, k
    loaded, chunks_done = ckpt.load_checkpoint(path, template, fingerprint)
    assert chunks_done == chunks
    for x, y in zip(jax.tree.leaves(loaded), jax.tree.leaves(runner)):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    with np.load(first.records if os.path.exists(first.records) else second.records) as z:
        other = {k: z[k] for k in z.files}
    other["lengths"] = other["lengths"] + 1
    np.savez(second.records, **other)
    with pytest.raises(ckpt.CheckpointError, match="holds other records than the checkpoint recorded"):
        ckpt.load_checkpoint(path, template, fingerprint)


# ---- the command line ------------------------------------------------------------------------------------------
_CLI_SETS = {"nsteps": "40", "chunk_steps": "15", "eval_episodes": "2", "eval_envs": "2", "bins": "[3, 6, 8, 10]",
             "state_low": "[-2.4, -1.0, -0.3, -2.0]", "state_high": "[2.4, 1.0, 0.3, 2.0]"}


def cli_tiny(nepisodes: int = 6, **sets: str) -> list[str]:
    """The tiny cart-pole run's CLI flags, with some ``--set`` values changed (each key once: the CLI refuses a
    key given twice)."""
    args = ["--env", "CartPoleStayUp-v0", "--n-envs", "4", "--nepisodes", str(nepisodes), "--no-progress"]
    for key, value in {**_CLI_SETS, **sets}.items():
        args += ["--set", f"{key}={value}"]
    return args


CLI_TINY = cli_tiny()


@pytest.fixture
def no_training(monkeypatch):
    """Fails the test if anything is traced or trained: refusals must come before."""
    def boom(*a, **k):
        raise AssertionError("compiled or trained before refusing")

    monkeypatch.setattr(ckpt, "carry_template", boom)
    monkeypatch.setattr(training, "train", boom)


def test_out_an_existing_file_or_a_nonempty_dir_is_refused_before_compiling(tmp_path, capsys, no_training):
    existing = tmp_path / "results.txt"
    existing.write_text("keep me")
    assert main(["train", *CLI_TINY, "--out", str(existing)]) == 2
    assert "--out" in capsys.readouterr().err and existing.read_text() == "keep me"
    assert main(["train", *CLI_TINY, "--out", str(existing / "run")]) == 2
    assert "is a file" in capsys.readouterr().err

    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text("{}")  # a run from before status.json existed
    (run / "config.yaml").write_text("{}")
    (run / "eval.csv").write_text("stale")
    assert main(["train", *CLI_TINY, "--out", str(run)]) == 2
    err = capsys.readouterr().err
    assert "not empty" in err and "--overwrite" in err
    other = tmp_path / "home"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert main(["train", *CLI_TINY, "--out", str(other), "--overwrite"]) == 2  # not a run: never replaced
    assert "run directories only" in capsys.readouterr().err
    assert sorted(os.listdir(run)) == ["config.yaml", "eval.csv", "summary.json"]
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # nothing staged

    assert main(["train", "--resume", str(run), "--no-progress"]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert main(["train", "--resume", str(run), "--seed", "3"]) == 2
    assert "drop --seed" in capsys.readouterr().err
    assert main(["train", *CLI_TINY, "--out", str(tmp_path / "x"), "--checkpoint-every", "-1"]) == 2
    assert "--checkpoint-every=-1" in capsys.readouterr().err


def test_check_out_names_the_flag_and_the_way_out(tmp_path):
    rundir.check_out(str(tmp_path / "new" / "run"))  # missing parents are fine
    rundir.check_out(str(tmp_path))  # an empty directory too
    run = tmp_path / "r"
    run.mkdir()
    rundir.write_status(str(run), rundir.INTERRUPTED)
    (run / rundir.CHECKPOINT).write_bytes(b"")
    with pytest.raises(ConfigError, match=r"--out .*interrupted run.*--overwrite.*--resume"):
        rundir.check_out(str(run))
    rundir.check_out(str(run), resume=True)
    assert rundir.is_resumable(str(run)) and not rundir.is_complete(str(run))


def test_overwrite_replaces_the_whole_old_run(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text("{}")
    (out / "config.yaml").write_text("{}")
    (out / "eval.csv").write_text("a stale evaluation of 400 rows")
    (out / "tensorboard").mkdir()
    assert main(["train", *cli_tiny(eval_episodes="0"), "--out", str(out), "--overwrite"]) == 0
    files = set(os.listdir(out))
    assert "eval.csv" not in files and {"summary.json", "episodes.csv", "qtables.npz", "status.json"} <= files
    assert rundir.is_complete(str(out)) and rundir.CHECKPOINT not in files
    assert not [n for n in files if n.startswith("checkpoint.")]  # nor the checkpoint's tables
    assert os.listdir(out / "tensorboard") and not [n for n in os.listdir(tmp_path) if n.startswith(".")]


def _wait_for(path: str, proc: subprocess.Popen, timeout: float = 240.0) -> None:
    end = time.monotonic() + timeout
    while not os.path.exists(path):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < end, f"{path} did not appear"
        time.sleep(0.05)


@pytest.mark.parametrize("sig", [signal.SIGINT])
def test_a_real_signal_leaves_a_resumable_run_that_resumes_to_the_uninterrupted_one(tmp_path, sig):
    """``jaxrobo train`` in a subprocess gets SIGINT once it has saved a checkpoint (one chunk per step, so that
    it is still training): it exits 130 with one line, no traceback, and a resumable directory with the episodes
    so far; ``--resume`` completes it to the run that was never interrupted."""
    args = cli_tiny(nepisodes=40, chunk_steps="1")
    out = str(tmp_path / "run")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": jax.config.jax_compilation_cache_dir or "off"}
    proc = subprocess.Popen([sys.executable, "-m", "jaxrobo.cli", "train", *args, "--checkpoint-every", "10",
                             "--out", out], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        _wait_for(os.path.join(out, rundir.CHECKPOINT), proc)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + sig, (stdout, stderr)
    assert "Traceback" not in stderr and f"--resume {out}" in stderr
    status = rundir.read_status(out)
    assert status["status"] == rundir.INTERRUPTED and status["signal"] == "SIGINT"
    assert 10 <= status["chunks_done"] < status["chunks"] and rundir.is_resumable(out)
    assert os.path.exists(os.path.join(out, "episodes.csv")) and not os.path.exists(os.path.join(out, "summary.json"))

    assert main(["train", "--resume", out, "--no-progress"]) == 0
    assert rundir.is_complete(out) and not [n for n in os.listdir(out) if n.startswith("checkpoint.")]
    full = str(tmp_path / "full")
    assert main(["train", *args, "--checkpoint-every", "0", "--out", full]) == 0
    _assert_same_run(out, full)


@pytest.mark.parametrize("budget", [[], ["--total-steps", "360"]], ids=["episodes", "steps"])
def test_a_finished_run_links_its_closing_checkpoints_records_and_tables(tmp_path, monkeypatch, budget):
    """A finished run's ``records.npz`` and ``qtables.npz`` are its closing checkpoint's files, linked, not written
    again; they hold what the results write themselves where a link is refused (the same run directory)."""
    from jaxrobo.io import results

    written, real = [], results.write_npz_deflated
    monkeypatch.setattr(results, "write_npz_deflated",
                        lambda path, **kw: (written.append(os.path.basename(path)), real(path, **kw))[1])
    linked = str(tmp_path / "linked")
    assert main(["train", *CLI_TINY, *budget, "--out", linked]) == 0
    assert written == [] and rundir.is_complete(linked)
    assert sorted(n for n in os.listdir(linked) if n.endswith(".npz")) == ["qtables.npz", "records.npz"]
    monkeypatch.setattr(results, "_linked", lambda source, path: False)
    copied = str(tmp_path / "copied")
    assert main(["train", *CLI_TINY, *budget, "--out", copied]) == 0
    assert sorted(written) == ["qtables.npz", "records.npz"]
    _assert_same_run(linked, copied)
    with np.load(os.path.join(linked, "records.npz")) as z:
        assert ("episodes_done" in z.files) == bool(budget)


def _counting_chunks(patch: pytest.MonkeyPatch) -> list:
    """A list that gets one item per compiled chunk run from now on (``driver.compiled_chunk`` wrapped)."""
    from jaxrobo.training import driver

    chunks_run = []
    real = driver.compiled_chunk

    def counting(*args, **kwargs):
        chunk = real(*args, **kwargs)
        return lambda *a: (chunks_run.append(1), chunk(*a))[1]

    patch.setattr(driver, "compiled_chunk", counting)
    return chunks_run


@pytest.fixture(scope="module")
def never_failed(tmp_path_factory):
    """The tiny CLI run that never failed, and how many chunks it ran."""
    full = str(tmp_path_factory.mktemp("never_failed") / "run")
    with pytest.MonkeyPatch.context() as patch:
        chunks_run = _counting_chunks(patch)
        assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", full]) == 0
    return full, len(chunks_run)


@pytest.mark.parametrize("overwrite", [False, True], ids=["new-out", "overwrite"])
def test_a_late_write_failure_leaves_the_finished_run_resumable_without_rerunning_chunks(tmp_path, monkeypatch,
                                                                                          capsys, never_failed,
                                                                                          overwrite):
    """The finished carry is checkpointed after the last chunk, before the evaluation and the writes (even with
    ``--checkpoint-every 0``): a write that fails then (a full disk under the TensorBoard log) leaves a run that
    ``--resume OUT`` finishes without running any chunk again, to the run that never failed, and the failure
    says so. With ``--overwrite`` the new run's state lives in a hidden sibling while it runs and stays there, the
    old run whole (an old run is replaced by a complete one only); ``--resume OUT`` continues the new run from
    there, not the old one it replaces."""
    from jaxrobo.io import results

    out = tmp_path / "run"
    if overwrite:
        out.mkdir()
        (out / "status.json").write_text(json.dumps({"status": "complete"}))  # an old finished run
        (out / "summary.json").write_text("{}")

    def full_disk(*_a, **_k):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(results, "write_tensorboard", full_disk)
        assert main(["train", *CLI_TINY, "--checkpoint-every", "0", "--out", str(out),
                     *(["--overwrite"] if overwrite else [])]) == 1  # one line, no traceback
    err = capsys.readouterr().err
    assert f"to go on: jaxrobo train --resume {out}" in err and "No space left on device" in err
    assert "Traceback" not in err
    hidden = sorted(n for n in os.listdir(tmp_path) if n.startswith("."))
    if overwrite:  # the new run's state beside the old run, which is whole
        assert len(hidden) == 1 and hidden[0].endswith(".partial")
        assert rundir.read_status(str(out)) == {"status": "complete"} and (out / "summary.json").read_text() == "{}"
        state = tmp_path / hidden[0]
    else:
        assert hidden == []
        state = out
    status = rundir.read_status(str(state))
    assert rundir.is_resumable(str(state)) and status["status"] == rundir.RUNNING and status["chunks_done"] > 0
    assert not os.path.exists(state / "summary.json")  # nothing half-written published

    chunks_run = _counting_chunks(monkeypatch)
    assert main(["train", "--resume", str(out), "--no-progress"]) == 0
    assert chunks_run == []
    final = rundir.read_status(str(out))
    assert final["status"] == rundir.COMPLETE and final["resumed_after_chunk"] == status["chunks_done"]
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]  # the sibling is gone once published
    full, full_chunks = never_failed
    assert full_chunks == status["chunks_done"]  # the same run from the start: every chunk
    _assert_same_run(str(out), full)


def test_changed_config_message(tmp_path, capsys):
    """The refusal of an edited config.yaml names what differs."""
    out = str(tmp_path / "run")
    spec = resolve("CartPoleStayUp-v0", overrides=CARTPOLE)
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    os.makedirs(out)
    from jaxrobo.io.results import write_config

    write_config(out, spec.to_dict())
    rundir.write_status(out, rundir.INTERRUPTED)
    runner = jax.jit(trainer.init)(jax.random.key(0), spec.agent_params, spec.env.default_params)
    ckpt.save_checkpoint(os.path.join(out, rundir.CHECKPOINT), runner, 0,
                             ckpt.carry_fingerprint(template, spec.to_dict()))
    text = open(os.path.join(out, "config.yaml")).read()
    open(os.path.join(out, "config.yaml"), "w").write(text.replace("alpha: 0.3", "alpha: 0.25"))
    assert main(["train", "--resume", out, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "refusing to resume" in err and "agent_params.alpha: 0.3 in the checkpoint vs 0.25 now" in err


@pytest.mark.slow
def test_a_run_with_snapshots_resumes_to_the_same_final_table(tmp_path):
    """The late tables kept for the final choice (QuadcopterGoto-v2's ``snapshots``) are part of the carry: a run
    stopped between them and resumed keeps the same snapshots, chooses the same table and reports the same choice."""
    spec = resolve("QuadcopterGoto-v2", overrides=dict(n_envs=2, nepisodes=10, nsteps=12, chunk_steps=12,
                                                       eval_episodes=2, snapshot_episodes=4))
    assert spec.config.snapshots > 0
    full = training.train(spec.env, spec.config, spec.agent_params)
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    fingerprint = ckpt.carry_fingerprint(template, spec.to_dict())
    path = str(tmp_path / rundir.CHECKPOINT)
    asked = []

    def should_stop():
        asked.append(1)
        return len(asked) > 4

    part = training.train(spec.env, spec.config, spec.agent_params, should_stop=should_stop,
                          checkpoint=lambda r, n: ckpt.save_checkpoint(path, r, n, fingerprint))
    assert not part.complete and part.final_table_choice is None  # a stopped run has not chosen
    runner, chunks_done = ckpt.load_checkpoint(path, template, fingerprint)
    resumed = training.train(spec.env, spec.config, spec.agent_params, initial=runner, start_chunk=chunks_done)
    for field in ("q", "returns", "lengths", "eval_returns", "eval_lengths", "eval_success"):
        np.testing.assert_array_equal(getattr(resumed, field), getattr(full, field), err_msg=field)
    assert resumed.final_table_choice == full.final_table_choice is not None


def test_large_records_are_cut_on_the_device_and_come_back_whole(tmp_path):
    """Records of 64 MB or more (:func:`jaxrobo.training.checkpoint.cut_records`) cross to the host cut to their
    written columns: the checkpoint keeps those (the widest env's episodes), the loader pads them back, and the
    result's records are the whole ``[envs, nepisodes]`` arrays, equal to the loaded ones."""
    spec = resolve("CartPoleStayUp-v0", overrides=dict(CARTPOLE, n_envs=64, nepisodes=120_000))
    trainer = Trainer(spec.env, spec.config)
    template = ckpt.carry_template(trainer, spec.agent_params)
    assert sum(np.prod(x.shape) * x.dtype.itemsize for x in (template.returns, template.lengths,
                                                               template.terminated)) >= 64 << 20
    fingerprint = ckpt.carry_fingerprint(template, spec.to_dict())
    path, asked = str(tmp_path / rundir.CHECKPOINT), []

    def should_stop():
        asked.append(1)
        return len(asked) > 2

    part = training.train(spec.env, spec.config, spec.agent_params, should_stop=should_stop,
                          checkpoint=lambda runner, chunks: ckpt.save_checkpoint(path, runner, chunks, fingerprint))
    assert not part.complete and part.returns.shape == (64, 120_000) and 0 < part.episodes_done.max() < 40
    with np.load(path, allow_pickle=False) as data:
        assert {data[k].shape for k in data if k.startswith("records_")} == {(64, int(part.episodes_done.max()))}
    runner, _ = ckpt.load_checkpoint(path, template, fingerprint)
    for name in ("returns", "lengths", "terminated"):
        np.testing.assert_array_equal(np.asarray(getattr(runner, name)), getattr(part, name), err_msg=name)
    assert part.lengths[:, :int(part.episodes_done.max())].any(axis=0).all() and not part.lengths[:, 40:].any()
