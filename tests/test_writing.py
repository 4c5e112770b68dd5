"""The writing of a run directory: what a person reads (``episodes.csv``, ``episode_stats.csv``, TensorBoard's
per-episode scalars) equals what the per-env records (``records.npz``) give, and ``qtables.npz`` the tables."""
from __future__ import annotations

import csv
import io
import os

import numpy as np
import pytest

from jaxrobo.io.results import EPISODE_COLUMNS, STAT_COLUMNS, read_columns, read_scalars, save_run, write_episodes
from jaxrobo.training.run import resolve
from jaxrobo.training.train import train
from jaxrobo.training.trainer import Trainer

#: A step budget: the envs record different numbers of episodes (some none past the first few).
STEPS = dict(n_envs=48, nepisodes=12, nsteps=60, chunk_steps=40, total_steps=48 * 160, eval_episodes=2, eval_envs=2,
             stop_at_target=False)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    spec = resolve("CartPoleStayUp-v0", overrides=STEPS)
    result = train(spec.env, spec.config, spec.agent_params)
    out = str(tmp_path_factory.mktemp("writing") / "run")
    save_run(out, result, spec.to_dict(), Trainer(spec.env, spec.config).disc)
    return result, out


def _records(out):
    with np.load(os.path.join(out, "records.npz"), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _csv_rows(records, done, max_envs):
    """``episodes.csv`` as the csv module writes it, row by row from the records."""
    f = io.StringIO(newline="")
    w = csv.writer(f)
    w.writerow(EPISODE_COLUMNS)
    for e in range(min(len(done), max_envs)):
        for i in range(int(done[e])):
            w.writerow((e, i, f"{records['returns'][e, i]:.6g}", int(records["lengths"][e, i]),
                        int(records["terminated"][e, i]), f"{records['epsilon'][i]:.6g}"))
    return f.getvalue()


def _stats(records, done):
    """Per episode index, over the envs that recorded it: mean, std, 10/50/90th percentiles of return and length."""
    out = {name: [] for name in STAT_COLUMNS}
    for i in range(int(done.max())):
        envs = done > i
        out["episode"].append(i)
        out["epsilon"].append(records["epsilon"][i])
        for name, key in (("return", "returns"), ("length", "lengths")):
            x = records[key][envs, i].astype(np.float64)
            out[f"{name}_mean"].append(x.mean())
            out[f"{name}_std"].append(x.std())
            for q in (10, 50, 90):
                out[f"{name}_p{q}"].append(np.percentile(x, q))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def test_the_files_a_person_reads_equal_what_the_records_give(run):
    result, out = run
    records = _records(out)
    done = records["episodes_done"]
    assert records["returns"].shape[0] == STEPS["n_envs"] and len(set(done.tolist())) > 1  # envs differ
    np.testing.assert_array_equal(done, result.episodes_done)
    assert open(os.path.join(out, "episodes.csv"), newline="").read() == _csv_rows(records, done, 1024)

    stats, expected = read_columns(os.path.join(out, "episode_stats.csv")), _stats(records, done)
    assert list(stats) == list(STAT_COLUMNS)
    for name in STAT_COLUMNS:  # the CSV keeps 6 significant digits: half a unit of the 6th is 5e-6 of the value at most
        np.testing.assert_allclose(stats[name], expected[name], rtol=5e-6, atol=1e-9, err_msg=name)

    scalars = read_scalars(os.path.join(out, "tensorboard"))
    for tag, name in (("episode/reward_mean", "return_mean"), ("episode/length_mean", "length_mean"),
                      ("episode/epsilon", "epsilon")):
        steps, values = zip(*scalars[tag])
        assert list(steps) == list(range(len(expected[name])))
        np.testing.assert_allclose(values, expected[name], rtol=1e-6, err_msg=tag)

    with np.load(os.path.join(out, "qtables.npz"), allow_pickle=False) as z:
        np.testing.assert_array_equal(z["q"], result.q)


def test_every_env_recording_each_episode_and_fewer_csv_envs(run, tmp_path):
    """The episode budget's case (every env recorded the same episodes) and the CSV's cap on envs."""
    result, _ = run
    n = int(result.episodes_done.min())
    assert n > 0
    returns, lengths, terminated = (np.asarray(x)[:, :n] for x in (result.returns, result.lengths,
                                                                    result.terminated))
    write_episodes(str(tmp_path), returns, lengths, terminated, result.epsilon, max_csv_envs=5)
    records = _records(str(tmp_path))
    done = np.full(returns.shape[0], n)
    assert "episodes_done" not in records and records["returns"].shape == returns.shape
    assert open(tmp_path / "episodes.csv", newline="").read() == _csv_rows(records, done, 5)
    stats, expected = read_columns(str(tmp_path / "episode_stats.csv")), _stats(records, done)
    for name in STAT_COLUMNS:
        np.testing.assert_allclose(stats[name], expected[name], rtol=5e-6, atol=1e-9, err_msg=name)


@pytest.mark.parametrize("compress", [True, False])
def test_npz_members_are_numpys_bytes_whoever_writes_the_blocks(monkeypatch, tmp_path, compress):
    """:func:`jaxrobo.io.npz.write_npz_deflated` writes each array's ``.npy`` bytes as numpy's ``write_array`` does,
    for contiguous, strided, Fortran, boolean, 0-d, empty and string arrays, cut into many blocks, by 1, 2 or 4
    threads (4: the mostly-zero blocks of a large array deflated, the others stored in the deflate stream), deflated
    or stored: ``zipfile`` finds every CRC right and ``np.load`` reads them back equal; pickles are refused."""
    import zipfile

    from jaxrobo.io import npz

    monkeypatch.setattr(npz, "BLOCK_BYTES", 64)  # several blocks per array
    monkeypatch.setattr(npz, "SMALL_BYTES", 1000)  # the larger arrays take the large arrays' path
    a = np.arange(1200, dtype=np.float32).reshape(40, 30)
    sparse = np.zeros((50, 40), np.float32)
    sparse[3, 4] = sparse[30, 1] = 1.5
    arrays = dict(a=a, cols=a[:, :7], strided=a[::3, 1:], fortran=a.T, flags=a[:, :5].astype(bool),
                  text=np.array("text"), scalar=np.array(3), empty=np.zeros((0, 4)), sparse=sparse,
                  mixed=np.concatenate([sparse.ravel(), a.ravel()]), odd=np.ones((3, 4, 5))[:, 1:3, ::2])
    sizes = {}
    for threads in (1, 2, 4):
        path = tmp_path / f"t{threads}.npz"
        npz.write_npz_deflated(str(path), compress=compress, threads=threads, **arrays)
        with zipfile.ZipFile(path) as zf:
            assert zf.testzip() is None
            for name, value in arrays.items():
                numpys = io.BytesIO()
                np.lib.format.write_array(numpys, value, allow_pickle=False)
                assert zf.read(f"{name}.npy") == numpys.getvalue(), (name, threads)
            sizes[threads] = {i.filename: (i.compress_type, i.compress_size) for i in zf.infolist()}
        with np.load(path, allow_pickle=False) as z:
            for name, value in arrays.items():
                np.testing.assert_array_equal(z[name], value)
    if compress:  # a large sparse array is deflated by 4 threads, stored with fewer; a small one always deflated
        assert sizes[4]["sparse.npy"][1] < sparse.nbytes / 4 and sizes[2]["sparse.npy"] == sizes[1]["sparse.npy"]
        assert sizes[2]["sparse.npy"][0] == zipfile.ZIP_STORED and sizes[1]["text.npy"][0] == zipfile.ZIP_DEFLATED
    else:
        assert {t for s in sizes.values() for t, _ in s.values()} == {zipfile.ZIP_STORED}
    with pytest.raises(ValueError, match="allow_pickle"):
        npz.write_npz_deflated(str(tmp_path / "pickled.npz"), x=np.array([object()]))


def test_npz_members_given_as_functions_are_called_in_their_turn(tmp_path):
    """A member given as a function is called once the members before it are written (a checkpoint's last members
    name the tables' file written meanwhile); one that returns a large array is refused, and the file not renamed
    in place by :func:`jaxrobo.io.rundir.atomic_savez`."""
    from jaxrobo.io import npz, rundir

    path, seen = tmp_path / "late.npz", []
    big = np.ones((1 << 16, 8))
    with open(path, "wb") as f:
        npz.write_npz_deflated(f, compress=False, big=big, name=lambda: (seen.append(f.tell()), np.array("x"))[1])
    assert seen[0] >= big.nbytes  # the large member was written before the function was called
    with np.load(path, allow_pickle=False) as z:
        assert z.files == ["big", "name"] and str(z["name"]) == "x" and np.array_equal(z["big"], big)
    target = tmp_path / "refused.npz"
    with pytest.raises(ValueError, match="late: an array given as a function must be at most"):
        rundir.atomic_savez(str(target), a=np.zeros(3), late=lambda: np.zeros(npz.SMALL_BYTES // 8 + 1))
    assert not target.exists()


def test_large_blocks_are_deflated_as_their_bytes_call_for(monkeypatch, tmp_path):
    """A large array's blocks written by 4 threads: mostly zeros shrink by run lengths, whole numbers at level 1,
    normal floats (which level 1 would grow) are copied; the CRC-32s of the blocks combined are the member's
    (``zipfile`` checks it) and ``np.load`` reads each array back."""
    import zipfile

    from jaxrobo.io import npz

    monkeypatch.setattr(npz, "SMALL_BYTES", 1000)
    monkeypatch.setattr(npz, "BLOCK_BYTES", 1 << 16)
    rng = np.random.default_rng(2)
    sparse = np.zeros(1 << 16, np.float32)
    sparse[rng.integers(0, sparse.size, 300)] = rng.random(300, np.float32)
    arrays = dict(sparse=sparse, whole=rng.integers(0, 1000, 1 << 16).astype(np.int32),
                  noise=rng.normal(size=1 << 16).astype(np.float32))
    path = tmp_path / "blocks.npz"
    npz.write_npz_deflated(str(path), threads=4, **arrays)
    with zipfile.ZipFile(path) as zf:
        assert zf.testzip() is None
        share = {i.filename[:-4]: i.compress_size / i.file_size for i in zf.infolist()}
    assert share["sparse"] < 0.1 and share["whole"] < npz.DENSE_RATIO and 1.0 <= share["noise"] < 1.01, share
    with np.load(path) as z:
        for name, value in arrays.items():
            np.testing.assert_array_equal(z[name], value)


def test_blocked_statistics_are_those_of_the_whole_arrays(run, monkeypatch):
    """``episode_stats`` over blocks of episode columns (a lone last column joining the block before it), in turn
    or by several threads, and the summary's figures over blocks of envs give the floats one block over the whole
    arrays gives."""
    from jaxrobo.io import results
    from jaxrobo.training import summary

    result, _ = run
    done = result.episodes_done
    returns, lengths = np.asarray(result.returns), np.asarray(result.lengths)
    n = int(done.min())
    cases = [(returns, lengths, done), (returns, lengths, np.minimum(done, 7)),  # 7 columns: a lone last one
             (returns[:, :n], lengths[:, :n], np.full(len(done), n))]  # every env recorded each column
    for r, ln, d in cases:
        monkeypatch.setattr(results, "STATS_BLOCK_BYTES", 1 << 40)
        whole = results.episode_stats(r, ln, result.epsilon, d)
        assert len(whole[0]) == int(d.max())
        for cols in (2, 3):
            for cores in (1, 4):  # the blocks computed in turn, or by a pool of threads
                # The means and spreads over blocks of a few envs, of envs up to the default size, or all at once.
                for moment_bytes in (8 * 3 * cols, results.MOMENT_BLOCK_BYTES, 1 << 40):
                    monkeypatch.setattr(results, "STATS_BLOCK_BYTES", 8 * len(d) * cols)
                    monkeypatch.setattr(results, "MOMENT_BLOCK_BYTES", moment_bytes)
                    blocked = results.episode_stats(r, ln, result.epsilon, d, threads=cores)
                    monkeypatch.undo()
                    for name, x, y in zip(STAT_COLUMNS, whole, blocked):
                        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), (name, cols, cores, moment_bytes)

    monkeypatch.setattr(summary, "FIGURE_BLOCK_ENVS", 1 << 30)
    whole = result.summary()
    monkeypatch.setattr(summary, "FIGURE_BLOCK_ENVS", 5)
    assert result.summary() == whole
    # The seed's figures, env by env, over the recorded episodes.
    envs = [e for e in range(len(done)) if done[e] > 0]
    highest = [returns[e, :done[e]].max() for e in envs]
    top = [np.sort(lengths[e, :done[e]])[-100:].mean() for e in envs]
    last = np.concatenate([returns[e, max(0, done[e] - 100):done[e]] for e in envs]).astype(np.float64)
    recorded = np.concatenate([lengths[e, :done[e]] for e in envs]).astype(np.float64)
    for name, value in (("highest_reward_mean", np.mean(highest)), ("highest_reward_max", np.max(highest)),
                        ("best_100_mean_length", np.mean(top)), ("final_100_mean_return", last.mean()),
                        ("overall_mean_length", recorded.mean())):
        assert whole[name] == pytest.approx(float(value), rel=1e-12), name


def test_npz_written_past_the_page_cache_is_the_same_file(monkeypatch, tmp_path):
    """Large stored arrays go through :class:`jaxrobo.io.npz.UncachedWrites` (``O_DIRECT`` for the aligned middle of
    each large write, the page cache for the rest): the file is byte for byte the one written through the page
    cache, whatever the alignments; where the file system has no ``O_DIRECT`` it is written as usual."""
    from jaxrobo.io import npz

    rng = np.random.default_rng(0)
    arrays = dict(q=rng.random((9, 1, 321, 7), dtype=np.float32), strided=rng.random((300, 1001))[:, 3:900],
                  small=np.arange(5), text=np.array("x" * 77))
    monkeypatch.setattr(npz, "SMALL_BYTES", 100)
    monkeypatch.setattr(npz, "BLOCK_BYTES", 300_000)  # stored blocks written as they are, several per array
    cached, uncached = tmp_path / "cached.npz", tmp_path / "uncached.npz"
    npz.write_npz_deflated(str(cached), **arrays)
    monkeypatch.setattr(npz, "UNCACHED_ABOVE_BYTES", 1)
    monkeypatch.setattr(npz.UncachedWrites, "DIRECT_FROM", 4096)
    monkeypatch.setattr(npz, "WRITE_CHUNK_BYTES", 40_000)  # several direct pieces per array, none aligned alike
    with open(uncached, "wb") as f:
        try:
            npz.UncachedWrites(f).close()
        except OSError:
            pytest.skip("no O_DIRECT on this file system")
    npz.write_npz_deflated(str(uncached), **arrays)
    assert uncached.read_bytes() == cached.read_bytes()
    with open(uncached, "r+b") as f:  # through an open file, as the checkpoint writes it
        npz.write_npz_deflated(f, **arrays)
    assert uncached.read_bytes() == cached.read_bytes()


def test_a_refused_direct_write_falls_back_to_the_page_cache(monkeypatch, tmp_path):
    """A device that opens ``O_DIRECT`` but refuses a 4096-aligned write (EINVAL: larger blocks) gets the rest of
    the file through the page cache: the same bytes, no error."""
    import errno

    from jaxrobo.io import npz

    arrays = dict(q=np.random.default_rng(1).random((64, 999), dtype=np.float32), small=np.arange(3))
    monkeypatch.setattr(npz, "SMALL_BYTES", 100)
    cached, uncached = tmp_path / "cached.npz", tmp_path / "uncached.npz"
    npz.write_npz_deflated(str(cached), **arrays)
    with open(uncached, "wb") as f:
        try:
            npz.UncachedWrites(f).close()
        except OSError:
            pytest.skip("no O_DIRECT on this file system")
    monkeypatch.setattr(npz, "UNCACHED_ABOVE_BYTES", 1)
    monkeypatch.setattr(npz.UncachedWrites, "DIRECT_FROM", 4096)
    monkeypatch.setattr(npz, "WRITE_CHUNK_BYTES", 40_000)
    refused = []
    pwrite = npz.UncachedWrites._pwrite

    def refuse_direct(self, fd, data, offset):
        if fd == self._direct:
            refused.append(offset)
            raise OSError(errno.EINVAL, "Invalid argument")
        return pwrite(self, fd, data, offset)

    monkeypatch.setattr(npz.UncachedWrites, "_pwrite", refuse_direct)
    npz.write_npz_deflated(str(uncached), **arrays)
    assert refused and uncached.read_bytes() == cached.read_bytes()


def test_records_cross_cut_to_their_written_columns_and_come_back_whole():
    """:func:`jaxrobo.training.checkpoint.cut_records` cuts a carry's episode records, on the device, to the columns
    up to the last one any of them wrote (the same arrays when cut again, so the checkpoint's thread and the result
    copy them once); :func:`~jaxrobo.training.checkpoint.pad_columns` gives the host copy its zeros back, in turn or
    by a thread per core: the arrays the whole records were."""
    import collections

    import jax.numpy as jnp

    from jaxrobo.training import checkpoint as ckpt

    Carry = collections.namedtuple("Carry", "q returns lengths terminated")
    rng = np.random.default_rng(3)
    done = rng.integers(0, 5, 37)
    written = np.arange(9)[None, :] < done[:, None]
    lengths = np.where(written, rng.integers(1, 30, (37, 9)), 0).astype(np.int32)
    returns = np.where(written, rng.normal(size=(37, 9)), 0).astype(np.float32)
    returns[done == done.max(), done.max() - 1] = 0.0  # a last episode of return 0: its lengths still say written
    carry = Carry(jnp.ones((37, 3)), jnp.asarray(returns), jnp.asarray(lengths), jnp.asarray(written & (lengths > 9)))
    assert ckpt.cut_records(carry) is carry  # small records cross whole
    cut = ckpt.cut_records(carry, from_bytes=0)
    assert cut.q is carry.q and all(x.shape == (37, done.max()) for x in cut[1:])
    again = ckpt.cut_records(carry._replace(q=None), from_bytes=0)
    assert all(a is b for a, b in zip(again[1:], cut[1:]))
    for threaded_from in (1 << 40, 0):  # in turn, then by a thread per core
        for whole, part in zip(carry[1:], cut[1:]):
            padded = ckpt.pad_columns(np.asarray(part), 9, threaded_from=threaded_from)
            assert padded.dtype == whole.dtype and np.array_equal(padded, np.asarray(whole))
            assert padded.flags.f_contiguous  # the zero columns are memory nothing writes
    empty = Carry(None, *(jnp.zeros((5, 4), d) for d in (jnp.float32, jnp.int32, bool)))
    assert all(x.shape == (5, 0) for x in ckpt.cut_records(empty, from_bytes=0)[1:])


@pytest.mark.parametrize("counts", ["masked", "equal"])
def test_the_figures_and_stats_are_the_same_for_records_in_either_order(counts, tmp_path):
    """A run that recorded fewer episodes than its slots hands its records over in Fortran order (pad_columns): the
    summary's figures, ``episode_stats.csv`` and ``records.npz`` hold the same numbers, bit for bit, as from the
    C-ordered arrays (numpy's reductions over the envs sum in the order of the memory they read; float returns
    whose sums round)."""
    from jaxrobo.io import results
    from jaxrobo.task.env import ranking
    from jaxrobo.training import summary as S
    from jaxrobo.training.checkpoint import pad_columns

    rng = np.random.default_rng(5)
    n, width, k = 3000, 400, 150
    done = rng.integers(k - 40, k + 1, n) if counts == "masked" else np.full(n, k - 20)
    written = np.arange(k)[None, :] < done[:, None]
    lengths = np.where(written, rng.integers(1, 500, (n, k)), 0).astype(np.int32)
    returns = np.where(written, lengths * np.float32(0.37) - rng.random((n, k), np.float32) * 11, 0).astype(np.float32)
    terminated = written & (lengths % 3 == 0)
    c_order = [np.ascontiguousarray(pad_columns(x, width)) for x in (returns, lengths, terminated)]
    f_order = [pad_columns(x, width) for x in (returns, lengths, terminated)]
    assert c_order[0].flags.c_contiguous and f_order[0].flags.f_contiguous
    eps = np.linspace(1.0, 0.0, width)
    got = {}
    for name, (r, ln, t) in {"C": c_order, "F": f_order}.items():
        w = int(done.max())
        mask = np.arange(w)[None, :] < done[:, None]
        figures = S._masked_figures(r[:, :w], ln[:, :w], mask)
        windows = [S.best_window(x[:, :w], mask, ranking(None)) for x in (r, ln)]
        stats = results.write_episodes(str(tmp_path / name), r, ln, t, eps, episodes_done=done)
        with np.load(tmp_path / name / "records.npz") as z:
            records = {key: z[key] for key in z.files}
        csv_text = (tmp_path / name / "episode_stats.csv").read_text() + (tmp_path / name / "episodes.csv").read_text()
        got[name] = (figures, windows, stats, records, csv_text)
    (fc, wc, sc, rc, tc), (ff, wf, sf, rf, tf) = got["C"], got["F"]
    assert fc == ff and wc == wf and tc == tf
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(sc, sf))
    assert rc.keys() == rf.keys() and all(np.array_equal(rc[key], rf[key]) for key in rc)


def _uncached_or_skip(path):
    from jaxrobo.io import npz

    with open(path, "wb") as f:
        try:
            npz.UncachedWrites(f).close()
        except OSError:
            pytest.skip("no O_DIRECT on this file system")


def test_uncached_writes_gather_write_in_a_thread_and_give_the_same_bytes(monkeypatch, tmp_path):
    """:class:`jaxrobo.io.npz.UncachedWrites` gathers the writes that follow a large one into page-aligned buffers
    written ``O_DIRECT`` by a thread while the caller fills the next (one buffer too: the caller waits for it):
    whatever the sizes, alignments and seeks back (a zip's patched headers), the file holds the bytes a plain file
    would, every direct write is whole pages at a page's offset, and the pages went direct."""
    import threading

    from jaxrobo.io import npz

    _uncached_or_skip(tmp_path / "probe")
    monkeypatch.setattr(npz.UncachedWrites, "DIRECT_FROM", 5000)
    monkeypatch.setattr(npz, "WRITE_CHUNK_BYTES", 3 * 4096 + 100)  # buffers of three pages
    rng = np.random.default_rng(7)
    ops = []
    for _ in range(300):
        kind = rng.random()
        if kind < 0.08:
            ops.append(("seek", int(rng.integers(0, 1 + sum(len(d) for k, d in ops if k == "write")))))
        elif kind < 0.12:
            ops.append(("end", 0))
        else:
            size = int(rng.choice([1, 30, 4095, 4096, 4097, 5000, 9000, 20_000, 70_000]))
            ops.append(("write", rng.integers(0, 256, size, dtype=np.uint8).tobytes()))
    pwrite, seen = npz.UncachedWrites._pwrite, []

    def spy(self, fd, data, offset):
        if fd == self._direct:
            seen.append((threading.current_thread().name, offset, memoryview(data).nbytes))
        return pwrite(self, fd, data, offset)

    monkeypatch.setattr(npz.UncachedWrites, "_pwrite", spy)
    for buffers in (1, 3):
        monkeypatch.setattr(npz.UncachedWrites, "BUFFERS", buffers)
        plain, uncached = tmp_path / f"plain{buffers}", tmp_path / f"uncached{buffers}"
        seen.clear()
        with open(plain, "wb") as p, open(uncached, "wb") as u:
            p.write(b"head")
            u.write(b"head")
            u.flush()
            w = npz.UncachedWrites(u)
            for kind, arg in ops:
                if kind == "write":
                    assert w.write(arg) == len(arg)
                    p.write(arg)
                elif kind == "seek":
                    assert w.seek(arg) == p.seek(arg)
                else:
                    w.flush()
                    assert w.seek(0, os.SEEK_END) == p.seek(0, os.SEEK_END)
                assert w.tell() == p.tell()
            w.close()
            assert not any(t.name.startswith("jaxrobo-direct-writes") for t in threading.enumerate())
        assert uncached.read_bytes() == plain.read_bytes()
        assert seen and all(name.startswith("jaxrobo-direct-writes") and offset % 4096 == 0 and n % 4096 == 0
                            for name, offset, n in seen)
        assert sum(n for _, _, n in seen) > plain.stat().st_size // 2


def test_uncached_writes_raise_the_thread_s_error_and_leave_no_thread(monkeypatch, tmp_path):
    """A direct write that fails (not EINVAL: a full or failing disk) is raised in the caller's thread by its next
    call (once: a close while it unwinds does not raise it again), and closing still stops the writing thread."""
    import errno
    import threading

    from jaxrobo.io import npz

    _uncached_or_skip(tmp_path / "probe")
    monkeypatch.setattr(npz.UncachedWrites, "DIRECT_FROM", 4096)
    monkeypatch.setattr(npz, "WRITE_CHUNK_BYTES", 8192)
    pwrite = npz.UncachedWrites._pwrite

    def fail(self, fd, data, offset):
        if fd == self._direct:
            raise OSError(errno.EIO, "Input/output error")
        return pwrite(self, fd, data, offset)

    monkeypatch.setattr(npz.UncachedWrites, "_pwrite", fail)
    with open(tmp_path / "x", "wb") as f:
        w = npz.UncachedWrites(f)
        with pytest.raises(OSError, match="Input/output"):
            for _ in range(20):
                w.write(bytes(20_000))
            w.flush()
        w.close()
        assert w.closed
    assert not any(t.name.startswith("jaxrobo-direct-writes") for t in threading.enumerate())
    with open(tmp_path / "y", "wb") as f:  # the same error found first by close (less than a buffer written)
        w = npz.UncachedWrites(f)
        w.write(bytes(6000))
        with pytest.raises(OSError, match="Input/output"):
            w.close()
        assert w.closed
