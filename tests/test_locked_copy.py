"""Large arrays' host copies through page-locked memory (jaxrobo.speed.locked_copy), run on the CPU with a stand-in
for the CUDA driver that copies what the driver would: the same bytes as jax.device_get's, each locked buffer
unlocked, one copy however often asked for, jax.device_get wherever the path does not apply or the driver fails,
and a whole command's files the same as with jax.device_get."""
from __future__ import annotations

import ctypes
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.cli import main
from jaxrobo.core.memo import IdentityMemo
from jaxrobo.speed import locked_copy
from jaxrobo.speed.locked_copy import DriverError


class StandIn:
    """The driver's calls on host memory: ``copy`` moves the bytes at the array's buffer pointer (a CPU array's is
    host memory) into the host buffer; ``fail`` names calls that return an error."""

    def __init__(self, fail=()):
        self.fail, self.locked, self.calls, self.copied = set(fail), set(), [], 0

    def _maybe_fail(self, name):
        self.calls.append(name)
        if name in self.fail:
            raise DriverError(f"{name} returned CUresult 1")

    def enter(self, ordinal):
        self._maybe_fail("enter")
        return ordinal, None

    def leave(self, device):
        self._maybe_fail("leave")

    def register(self, host, nbytes):
        self._maybe_fail("register")
        self.locked.add(host)

    def unregister(self, host):
        self._maybe_fail("unregister")
        self.locked.remove(host)

    def copy(self, pairs):
        self._maybe_fail("copy")
        for host, device, nbytes in pairs:
            ctypes.memmove(host, device, nbytes)
            self.copied += 1


@pytest.fixture
def stand_in(monkeypatch):
    driver = StandIn()
    monkeypatch.setattr(locked_copy, "_driver", lambda: driver)
    monkeypatch.setattr(locked_copy, "_COPIES", IdentityMemo())
    return driver


def _arrays():
    rng = np.random.default_rng(0)
    whole = rng.normal(size=(300, 40)).astype(np.float32)
    return {"returns": jnp.asarray(whole)[:, :17],  # a cut: a fresh array of its own on the device
            "lengths": jnp.asarray(rng.integers(-5, 500, size=(300, 23), dtype=np.int32)),
            "terminated": jnp.asarray(rng.random((257, 9)) < 0.5),
            "wide": jnp.asarray(rng.normal(size=(64, 3, 5))),
            "small": jnp.arange(3), "none": None, "number": 7}


def test_the_copies_are_the_arrays_bytes_and_every_locked_buffer_is_unlocked(stand_in):
    tree = _arrays()
    host = locked_copy.get(tree, from_bytes=64, on_cpu=True)
    plain = jax.device_get(tree)
    assert stand_in.copied == 4 and not stand_in.locked  # "small" (24 bytes) went through jax.device_get
    assert stand_in.calls.count("register") == stand_in.calls.count("unregister") == 4
    assert host["none"] is None and host["number"] == 7
    for name, x in tree.items():
        if isinstance(x, jax.Array):
            assert isinstance(host[name], np.ndarray) and host[name].dtype == x.dtype and host[name].shape == x.shape
            assert host[name].tobytes() == np.asarray(plain[name]).tobytes(), name
            assert not host[name].flags.writeable  # read-only, as jax.device_get's copies
    assert host["returns"].flags.c_contiguous


def test_the_fault_blocks_cover_each_buffer_once():
    sizes = [0, 1, 4096 * 3, 4096 * 7 + 5]
    blocks = locked_copy._fault_blocks(sizes, 4096 * 3)
    for i, n in enumerate(sizes):
        mine = [(a, b) for j, a, b in blocks if j == i]
        assert [a for a, _ in mine] == list(range(0, n, 4096 * 3)) and all(b - a <= 4096 * 3 for a, b in mine)
        assert all(b == a2 for (_, b), (a2, _) in zip(mine, mine[1:])) and (not mine or mine[-1][1] == n)


def test_the_same_array_asked_again_by_two_threads_is_copied_once(stand_in):
    x = jnp.asarray(np.arange(5000, dtype=np.int32).reshape(100, 50))
    got = []
    threads = [threading.Thread(target=lambda: got.append(locked_copy.get(x, from_bytes=0, on_cpu=True)))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert stand_in.copied == 1 and got[0] is got[1]
    assert locked_copy.get([x], from_bytes=0, on_cpu=True)[0] is got[0]


@pytest.mark.parametrize("fail", ["register", "copy", "enter", "unregister", "leave"])
def test_a_failing_driver_loses_nothing(stand_in, fail):
    """The copy without locking where locking fails; jax.device_get where the copy fails; a buffer still locked
    is never handed out."""
    stand_in.fail = {fail}
    tree = _arrays()
    host = locked_copy.get(tree, from_bytes=64, on_cpu=True)
    for name, x in tree.items():
        if isinstance(x, jax.Array):
            assert host[name].tobytes() == np.asarray(x).tobytes(), name
    if fail in ("register", "leave"):
        assert stand_in.copied == 4 and not stand_in.locked
    if fail in ("copy", "enter"):
        assert stand_in.copied == 0 and not stand_in.locked
    if fail == "unregister":
        assert all(x.ctypes.data in stand_in.locked for x in locked_copy._STILL_LOCKED[-4:])
        assert not any(host[name].ctypes.data in stand_in.locked for name in ("returns", "lengths", "wide"))
    assert stand_in.calls.count("enter") == 1 and stand_in.calls.count("leave") == (fail != "enter")


def test_where_the_path_does_not_apply(monkeypatch):
    x = jnp.zeros((64, 64))
    assert locked_copy.why_not(x, from_bytes=0) == "on a cpu device"
    assert locked_copy.why_not(x, from_bytes=0, on_cpu=True) is None
    assert "bytes, under" in locked_copy.why_not(x, on_cpu=True)
    assert locked_copy.why_not(np.zeros(3)) == "not a jax.Array"
    assert locked_copy.why_not(jnp.zeros((4, 4), jnp.complex64), from_bytes=0, on_cpu=True) == "dtype complex64"
    host = locked_copy.get(x)  # the CPU: jax.device_get, no driver
    assert host.tobytes() == np.asarray(x).tobytes()
    monkeypatch.setattr(jax, "__version__", "0.99.0")
    locked_copy._version_outside.cache_clear()
    try:
        reason = locked_copy.why_not(x, from_bytes=0, on_cpu=True)
        assert reason is not None and "jax 0.99.0 is outside the versions" in reason and ">= 0.10, < 0.12" in reason
    finally:
        monkeypatch.undo()
        locked_copy._version_outside.cache_clear()
    assert locked_copy._version_outside() is None  # this JAX is one it was written for


def test_no_driver_library_falls_back(monkeypatch):
    def missing():
        raise OSError("libcuda.so.1: cannot open shared object file")

    monkeypatch.setattr(locked_copy, "_driver", missing)
    monkeypatch.setattr(locked_copy, "_COPIES", IdentityMemo())
    x = jnp.arange(4096, dtype=jnp.float32).reshape(64, 64)
    assert locked_copy.get(x, from_bytes=0, on_cpu=True).tobytes() == np.asarray(x).tobytes()


def _directory(out):
    files = {}
    for root, _, names in os.walk(out):
        for name in names:
            path = os.path.join(root, name)
            rel = os.path.relpath(path, out)
            if rel in ("summary.json", "status.json") or rel.startswith("tensorboard"):
                continue  # timings and wall clocks
            with open(path, "rb") as f:
                files[rel] = f.read()
    return files


def test_a_run_whose_arrays_cross_through_the_driver_writes_the_same_files(tmp_path, monkeypatch, stand_in):
    """The whole command, its closing checkpoint and its result copying through the stand-in driver: the run
    directory's files the same bytes as jax.device_get's run."""
    args = ["train", "--env", "CartPoleStayUp-v0", "--n-envs", "16", "--nepisodes", "8", "--no-progress",
            "--set", "nsteps=40", "--set", "chunk_steps=20", "--set", "eval_episodes=2", "--set", "eval_envs=2"]
    assert main([*args, "--out", str(tmp_path / "plain")]) == 0
    assert stand_in.copied == 0
    original = locked_copy.get
    monkeypatch.setattr(locked_copy, "get", lambda tree, **_: original(tree, from_bytes=256, on_cpu=True))
    assert main([*args, "--out", str(tmp_path / "locked")]) == 0
    assert stand_in.copied > 0 and not stand_in.locked
    plain, locked = _directory(tmp_path / "plain"), _directory(tmp_path / "locked")
    assert sorted(plain) == sorted(locked)
    for name in plain:
        assert plain[name] == locked[name], name
