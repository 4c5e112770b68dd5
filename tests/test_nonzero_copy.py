"""The tables' host copy made from their nonzero entries (jaxrobo.training.nonzero_copy): the same values bit for bit,
the same file bytes, one copy however often asked for, and a run's files the same as with the plain copy."""
from __future__ import annotations

import functools
import io
import os
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.cli import main
from jaxrobo.io import npz
from jaxrobo.training import nonzero_copy
from jaxrobo.training.nonzero_copy import NonzeroCopy, host_copy
from jaxrobo.training.summary import TrainResult


def _sparse(shape, share, seed=0):
    """Mostly zeros, a few -0.0 and a NaN's bits among the others (bits, not values, are what is kept)."""
    rng = np.random.default_rng(seed)
    a = np.zeros(shape, np.float32)
    nonzero = rng.random(shape) < share
    a[nonzero] = rng.normal(size=int(nonzero.sum())).astype(np.float32)
    flat = a.reshape(-1)
    flat[: min(3, flat.size)] = -0.0
    flat[-1:] = np.nan
    return a


def _npz_bytes(q, threads):
    f = io.BytesIO()
    npz.write_npz_deflated(f, q=q, threads=threads)
    return f.getvalue()


@pytest.mark.parametrize("shape", [(3, 5, 7, 2), (37, 1, 101, 3), (2, 1, 1024, 2)])
def test_the_copy_is_the_array_bit_for_bit_and_writes_the_same_file(monkeypatch, shape):
    monkeypatch.setattr(npz, "BLOCK_BYTES", 1024)  # several blocks, and a last one cut short
    a = _sparse(shape, 0.1)
    copy = host_copy(jnp.asarray(a), from_bytes=0, on_cpu=True)
    assert isinstance(copy, NonzeroCopy) and copy.shape == a.shape and copy.dtype == a.dtype
    assert int(copy.counts.sum()) == np.count_nonzero(a.view(np.uint32)) <= copy.values.size
    assert copy.bits.nbytes == -(-a.size // 8)
    assert copy.dense().tobytes() == a.tobytes()
    assert np.asarray(copy[None]).tobytes() == a.tobytes() and copy[None].shape == (1, *a.shape)
    for threads in (1, 4):  # stored, and deflated block by block: the same bytes as the dense array's file
        assert _npz_bytes(copy, threads) == _npz_bytes(a, threads)
    with np.load(io.BytesIO(_npz_bytes(copy, 4)), allow_pickle=False) as z:
        assert z["q"].tobytes() == a.tobytes()


@pytest.mark.parametrize("shape", [(13, 5, 7, 2), (64, 1, 64, 2)])
def test_blocks_deflated_on_the_device_write_a_file_of_the_same_arrays(monkeypatch, shape):
    """The whole blocks' streams made on the device (jaxrobo.speed.device_deflate), a last block cut short (or none)
    deflated on the host: the file holds the same arrays and passes zip's CRC checks, whatever the threads."""
    monkeypatch.setattr(npz, "BLOCK_BYTES", 1024)
    monkeypatch.setattr(nonzero_copy, "host_copy", functools.partial(host_copy, from_bytes=0, on_cpu=True))
    a = _sparse(shape, 0.1)
    x = jnp.asarray(a)
    assert nonzero_copy.file_copy(x).deflated is None  # under DEFLATE_FROM_BYTES: the host deflates
    copy = nonzero_copy.file_copy(x, deflate_from=0)
    assert copy.deflated is not None and len(copy.deflated.crc) == a.nbytes // 1024
    assert nonzero_copy.host_copy(x).deflated is None  # the copy other callers get: made first, not waiting
    files = {threads: _npz_bytes(copy, threads) for threads in (1, 4)}
    assert files[1] == files[4] != _npz_bytes(a, 4)
    with zipfile.ZipFile(io.BytesIO(files[1])) as zf:
        assert zf.testzip() is None and zf.getinfo("q.npy").compress_type == zipfile.ZIP_DEFLATED
    with np.load(io.BytesIO(files[1]), allow_pickle=False) as z:
        assert z["q"].tobytes() == a.tobytes()
    assert copy.reshape(a.size).deflated is copy.deflated and copy[None].deflated is copy.deflated


def test_the_same_array_is_copied_once_and_the_plain_copy_where_it_would_not_pay():
    a = _sparse((64, 1, 50, 2), 0.05)
    x = jnp.asarray(a)
    first = host_copy(x, from_bytes=0, on_cpu=True)
    assert host_copy(x, from_bytes=0, on_cpu=True) is first
    dense = host_copy(jnp.asarray(_sparse((64, 1, 50, 2), 0.9)), from_bytes=0, on_cpu=True)
    assert isinstance(dense, np.ndarray)  # most entries nonzero: the plain copy
    small = host_copy(jnp.asarray(a), on_cpu=True)  # under FROM_BYTES
    assert isinstance(small, np.ndarray) and small.tobytes() == a.tobytes()
    on_cpu = host_copy(jnp.asarray(a), from_bytes=0)  # a CPU array is host memory already
    assert isinstance(on_cpu, np.ndarray)
    with pytest.raises(TypeError):
        first[0]
    with pytest.raises(ValueError, match="cannot reshape"):
        first.reshape(3, -1)


def test_a_result_given_the_copy_reads_its_tables_dense_once():
    a = _sparse((8, 1, 40, 2), 0.1)
    copy = host_copy(jnp.asarray(a), from_bytes=0, on_cpu=True)
    result = TrainResult(env_id="x", config=None, agent_params=None, returns=np.zeros((8, 1)),
                         lengths=np.zeros((8, 1)), terminated=np.zeros((8, 1), bool), epsilon=np.zeros(1),
                         nan_episodes=np.zeros(8), env_steps=0, q=copy, compile_seconds=0.0, run_seconds=0.0)
    assert result.tables is copy
    q = result.q
    assert isinstance(q, np.ndarray) and q.tobytes() == a.tobytes() and result.q is q and result.tables is q
    result.q = a
    assert result.q is a


def _files(out):
    with np.load(os.path.join(out, "qtables.npz"), allow_pickle=False) as z:
        tables = {k: z[k] for k in z.files}
    with open(os.path.join(out, "qtables.npz"), "rb") as f:
        return tables, f.read()


def test_a_run_whose_tables_cross_as_their_nonzero_entries_writes_the_same_files(tmp_path, monkeypatch):
    """The whole command, its closing checkpoint and its result copying the tables as on an accelerator (forced on
    the CPU): qtables.npz the same bytes as the plain copy's run."""
    args = ["train", "--env", "CartPoleStayUp-v0", "--n-envs", "16", "--nepisodes", "8", "--no-progress",
            "--set", "nsteps=40", "--set", "chunk_steps=20", "--set", "eval_episodes=2", "--set", "eval_envs=2"]
    assert main([*args, "--out", str(tmp_path / "plain")]) == 0
    made = []
    original = nonzero_copy.host_copy

    def forced(x, **_):
        copy = original(x, from_bytes=0, on_cpu=True)
        made.append(copy)
        return copy

    monkeypatch.setattr(nonzero_copy, "host_copy", forced)
    assert main([*args, "--out", str(tmp_path / "nonzero")]) == 0
    assert made and all(isinstance(c, NonzeroCopy) for c in made)
    assert made[0] is made[-1]  # the checkpoint's and the result's copy: one crossing
    plain, nonzero = _files(tmp_path / "plain"), _files(tmp_path / "nonzero")
    assert plain[1] == nonzero[1]
    for k in plain[0]:
        np.testing.assert_array_equal(plain[0][k], nonzero[0][k], err_msg=k)


def test_a_run_whose_tables_are_deflated_on_the_device_writes_the_same_tables(tmp_path, monkeypatch):
    """As above with blocks of 4 KB, deflated on the device (forced on the CPU): other bytes, the same arrays, a
    file whose CRCs hold."""
    monkeypatch.setattr(npz, "BLOCK_BYTES", 4096)
    args = ["train", "--env", "CartPoleStayUp-v0", "--n-envs", "16", "--nepisodes", "8", "--no-progress",
            "--set", "nsteps=40", "--set", "chunk_steps=20", "--set", "eval_episodes=2", "--set", "eval_envs=2"]
    assert main([*args, "--out", str(tmp_path / "plain")]) == 0
    made = []
    original = nonzero_copy.file_copy

    def kept(x):
        made.append(original(x, deflate_from=0))
        return made[-1]

    monkeypatch.setattr(nonzero_copy, "host_copy", functools.partial(host_copy, from_bytes=0, on_cpu=True))
    monkeypatch.setattr(nonzero_copy, "file_copy", kept)
    assert main([*args, "--out", str(tmp_path / "device")]) == 0
    assert made and made[-1].deflated is not None and len(made[-1].deflated.crc) > 1
    plain, device = _files(tmp_path / "plain"), _files(tmp_path / "device")
    assert plain[1] != device[1]
    for k in plain[0]:
        np.testing.assert_array_equal(plain[0][k], device[0][k], err_msg=k)
    with zipfile.ZipFile(tmp_path / "device" / "qtables.npz") as zf:
        assert zf.testzip() is None


def test_the_host_deflates_when_the_device_cannot(monkeypatch):
    """The blocks' programs out of the device's memory: the copy without them, the file the host's (the same bytes
    as the dense array's)."""
    def fail(*a, **k):
        raise RuntimeError("RESOURCE_EXHAUSTED: out of memory")

    monkeypatch.setattr(npz, "BLOCK_BYTES", 1024)
    monkeypatch.setattr(nonzero_copy, "host_copy", functools.partial(host_copy, from_bytes=0, on_cpu=True))
    monkeypatch.setattr(nonzero_copy.device_deflate, "_measure", fail)
    a = _sparse((16, 1, 30, 2), 0.1)
    copy = nonzero_copy.file_copy(jnp.asarray(a), deflate_from=0)
    assert isinstance(copy, NonzeroCopy) and copy.deflated is None
    assert _npz_bytes(copy, 4) == _npz_bytes(a, 4)


def test_the_plain_copy_when_the_programs_fail(monkeypatch):
    """A device out of memory for the mask's or the gather's temporaries: the plain copy, nothing lost."""
    def fail(*a, **k):
        raise RuntimeError("RESOURCE_EXHAUSTED: out of memory")

    monkeypatch.setattr(nonzero_copy, "_mask", fail)
    a = _sparse((16, 1, 30, 2), 0.1)
    copy = functools.partial(host_copy, from_bytes=0, on_cpu=True)(jnp.asarray(a))
    assert isinstance(copy, np.ndarray) and copy.tobytes() == a.tobytes()


def test_nothing_compiles_ahead_for_arrays_that_cross_whole_or_on_a_cpu():
    assert nonzero_copy.prepare(jnp.zeros((1024, 1024), jnp.float32)) == []  # a CPU array
    assert nonzero_copy.prepare(jax.ShapeDtypeStruct((8, 1, 480, 4), jnp.float32)) == []  # the default device: a CPU


def test_nothing_compiles_ahead_for_a_cpu_array_or_one_that_crosses_whole():
    big = jax.ShapeDtypeStruct((1 << 28,), jnp.float32)  # 1 GiB, on the default device: a CPU here
    assert nonzero_copy.prepare(big) == [] and nonzero_copy.prepare(jnp.zeros((8, 1, 40, 2))) == []
    assert nonzero_copy._taken(big, [jax.devices()[0]], 0, on_cpu=True, itemsizes=(4,))
    assert not nonzero_copy._taken(big, [jax.devices()[0]], 0, on_cpu=False, itemsizes=(4,))
    assert not nonzero_copy._taken(big, [jax.devices()[0]], 1 << 31, on_cpu=True, itemsizes=(4,))
