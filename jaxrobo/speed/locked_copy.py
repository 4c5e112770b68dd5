"""Large GPU arrays copied to the host through page-locked memory: the host buffer's pages faulted in by a thread
per core, locked for the copy (``cuMemHostRegister``), filled by the CUDA driver, unlocked.

Why: on a GPU host a large array's copy into fresh host memory goes at the rate one thread faults its pages in:
``jax.device_get`` took 2.0-3.7 s for a 1 M-env run's cut episode records (3.1 GB) in a fresh process on an H200
host, and 0.25-0.38 s this way; the copy into memory already locked runs at 54 GB/s, and faulting the pages in on
one thread took 0.45-0.95 s. JAX's own pinned host memory (``memory_kind="pinned_host"``) does not help a copy made
once: its first allocation, locked by the driver on one thread, took 2.4 s for those records. The 1 M-env run's
writing went from 6.0-7.1 s to 4.9-6.0 s (``benchmarks/results/h200/locked_copy_s34.json``).

This reaches past JAX: the CUDA driver (``libcuda.so.1`` through :mod:`ctypes`) reads the array's device memory at
its :meth:`jax.Array.unsafe_buffer_pointer`. So it is used only on JAX versions in :data:`WRITTEN_FOR`, for arrays
on one CUDA device of :data:`FROM_BYTES` or more, in the default row-major layout, of bool, integer or float dtypes
(:func:`why_not` says why an array is not); anything else, and any error from the driver, goes through
``jax.device_get``. The bytes are the array's either way: ``tests/test_locked_copy.py`` runs the whole path on the
CPU with a stand-in for the driver (and checks the fallbacks), and the benchmark above compares the GPU's copies
with ``jax.device_get``'s.

Public surface: :func:`get`, :func:`why_not`, :data:`FROM_BYTES`, :data:`WRITTEN_FOR`.
"""
from __future__ import annotations

import ctypes
import functools
from typing import Any

import jax
import numpy as np

from jaxrobo.core.environ import in_threads
from jaxrobo.core.memo import IdentityMemo
from jaxrobo.core.version import outside

#: JAX versions ``[low, high)`` this was written and tested for (0.10 on CPU with the stand-in driver; 0.11.2 on an
#: H200).
WRITTEN_FOR = ((0, 10), (0, 12))
#: Arrays smaller than this go through ``jax.device_get`` (locking and unlocking their pages costs about what the
#: copy saves).
FROM_BYTES = 64 << 20
#: Bytes of host memory a thread faults in at a time.
FAULT_BLOCK = 64 << 20
#: The host's page: one byte written in each faults it in.
PAGE = 4096


class DriverError(RuntimeError):
    """A CUDA driver call that did not return ``CUDA_SUCCESS``."""


class _Driver:
    """The few CUDA driver calls a copy needs (``libcuda.so.1``), each raising :class:`DriverError` on failure."""

    def __init__(self) -> None:
        self.lib = ctypes.CDLL("libcuda.so.1")

    def _call(self, name: str, *args: Any) -> None:
        rc = getattr(self.lib, name)(*args)
        if rc != 0:
            raise DriverError(f"{name} returned CUresult {rc}")

    def enter(self, ordinal: int) -> tuple[ctypes.c_int, ctypes.c_void_p]:
        """The device's primary context (the one JAX's client uses) made current in this thread."""
        self._call("cuInit", 0)
        device, context = ctypes.c_int(), ctypes.c_void_p()
        self._call("cuDeviceGet", ctypes.byref(device), ordinal)
        self._call("cuDevicePrimaryCtxRetain", ctypes.byref(context), device)
        try:
            self._call("cuCtxPushCurrent_v2", context)
        except DriverError:
            self._call("cuDevicePrimaryCtxRelease_v2", device)
            raise
        return device, context

    def leave(self, device: ctypes.c_int) -> None:
        self._call("cuCtxPopCurrent_v2", ctypes.byref(ctypes.c_void_p()))
        self._call("cuDevicePrimaryCtxRelease_v2", device)

    def register(self, host: int, nbytes: int) -> None:
        self._call("cuMemHostRegister_v2", ctypes.c_void_p(host), ctypes.c_size_t(nbytes), 0)

    def unregister(self, host: int) -> None:
        self._call("cuMemHostUnregister", ctypes.c_void_p(host))

    def copy(self, pairs: list[tuple[int, int, int]]) -> None:
        """Each ``(host, device, nbytes)`` copied from the device, on a stream of its own that waits for no other
        (the arrays are ready), then waited for."""
        stream = ctypes.c_void_p()
        self._call("cuStreamCreate", ctypes.byref(stream), 1)  # CU_STREAM_NON_BLOCKING
        try:
            for host, device, nbytes in pairs:
                self._call("cuMemcpyDtoHAsync_v2", ctypes.c_void_p(host), ctypes.c_uint64(device),
                           ctypes.c_size_t(nbytes), stream)
        finally:  # whatever was queued lands before its buffers are unlocked or let go, even after a failed call
            synced = self.lib.cuStreamSynchronize(stream)
            self.lib.cuStreamDestroy_v2(stream)
        if synced != 0:
            raise DriverError(f"cuStreamSynchronize returned CUresult {synced}")


@functools.cache
def _driver() -> _Driver:
    return _Driver()


@functools.cache
def _version_outside() -> str | None:
    return outside("jax", jax.__version__, WRITTEN_FOR, "the copy through the CUDA driver")


def why_not(x: Any, *, from_bytes: int | None = None, on_cpu: bool = False) -> str | None:
    """Why ``x`` is copied by ``jax.device_get`` rather than through page-locked memory (None: it is not).
    ``on_cpu``: a CPU array is taken as a device's (tests, with a stand-in driver)."""
    if not isinstance(x, jax.Array):
        return "not a jax.Array"
    reason = _version_outside()
    if reason is not None:
        return reason
    if x.nbytes < (FROM_BYTES if from_bytes is None else from_bytes):
        return f"{x.nbytes} bytes, under {FROM_BYTES if from_bytes is None else from_bytes}"
    devices = x.devices()
    if len(devices) != 1 or not x.is_fully_addressable:
        return "not on one device of this process"
    platform = next(iter(devices)).platform
    if platform != "gpu" and not (on_cpu and platform == "cpu"):
        return f"on a {platform} device"
    if platform == "gpu" and "cuda" not in str(next(iter(devices)).client.platform_version).lower():
        return "not a CUDA GPU"
    if getattr(x.sharding, "memory_kind", None) not in (None, "device"):
        return f"in {x.sharding.memory_kind} memory"
    dtype = np.dtype(x.dtype)
    if dtype.kind not in "biuf" or dtype.itemsize * x.size != x.nbytes:
        return f"dtype {dtype}"
    layout = getattr(getattr(x, "format", None), "layout", None)
    order = getattr(layout, "major_to_minor", None)
    if order is not None and tuple(order) != tuple(range(x.ndim)):
        return f"layout {tuple(order)}, not row-major"
    if getattr(layout, "tiling", None):
        return "a tiled layout"
    return None


_STILL_LOCKED: list[np.ndarray] = []
#: Every array's copy while the array lives (a run's records and its tables' mask and values).
_COPIES = IdentityMemo()


def _fault_blocks(sizes: list[int], block: int) -> list[tuple[int, int, int]]:
    """``(buffer, start, stop)`` for each block of at most ``block`` bytes of buffers of ``sizes`` bytes, in order:
    together they cover every byte of each once."""
    return [(i, a, min(a + block, n)) for i, n in enumerate(sizes) for a in range(0, n, block)]


def _through_driver(arrays: list[jax.Array]) -> list[np.ndarray | None]:
    """The arrays' host copies (None where the driver failed: the caller copies those with ``jax.device_get``)."""
    driver = _driver()
    out = [np.empty(x.shape, x.dtype) for x in arrays]
    flat = [o.reshape(-1).view(np.uint8) for o in out]
    blocks = _fault_blocks([f.size for f in flat], FAULT_BLOCK)

    def fault(k: int, _: int) -> None:
        i, a, b = blocks[k]
        flat[i][a:b:PAGE] = 0

    in_threads(fault, list(range(len(blocks))), list(range(len(blocks))), name="jaxrobo-fault")
    jax.block_until_ready(arrays)
    by_device: dict[int, list[int]] = {}
    for i, x in enumerate(arrays):
        by_device.setdefault(next(iter(x.devices())).local_hardware_id or 0, []).append(i)
    done: list[np.ndarray | None] = [None] * len(arrays)
    for ordinal, index in by_device.items():
        try:
            device, _ = driver.enter(ordinal)
        except DriverError:
            continue
        registered = []
        try:
            for i in index:
                try:  # unlocked memory is copied too, staged by the driver (slower, still faulted in already)
                    driver.register(out[i].ctypes.data, out[i].nbytes)
                    registered.append(i)
                except DriverError:
                    pass
            driver.copy([(out[i].ctypes.data, arrays[i].unsafe_buffer_pointer(), out[i].nbytes) for i in index])
            for i in index:
                done[i] = out[i]
        except DriverError:
            pass
        finally:
            for i in registered:
                try:
                    driver.unregister(out[i].ctypes.data)
                except DriverError:  # a buffer still locked is neither handed out nor freed
                    done[i] = None
                    _STILL_LOCKED.append(out[i])
            try:
                driver.leave(device)
            except DriverError:  # the copies are whole; the context stays current in this thread
                pass
    return done


def get(tree: Any, *, from_bytes: int | None = None, on_cpu: bool = False) -> Any:
    """``jax.device_get(tree)``, its large arrays on a CUDA GPU (:func:`why_not`) copied through page-locked memory.
    The host copies are read-only, as ``jax.device_get``'s are; the same array asked for again while it lives (by
    another thread too) gives the same copy, made once."""
    leaves, treedef = jax.tree.flatten(tree)
    wanted = [i for i, x in enumerate(leaves) if why_not(x, from_bytes=from_bytes, on_cpu=on_cpu) is None]
    if not wanted:
        return jax.device_get(tree)
    host = list(leaves)
    with _COPIES.lock:
        todo = []
        for i in wanted:
            hit = _COPIES.get(leaves[i])
            if hit is not None:
                host[i] = hit
            else:
                todo.append(i)
        try:
            copies = _through_driver([leaves[i] for i in todo]) if todo else []
        except (OSError, AttributeError):  # no libcuda.so.1, or one without these calls
            copies = [None] * len(todo)
        for i, copy in zip(todo, copies):
            if copy is None:
                copy = np.asarray(jax.device_get(leaves[i]))
            else:
                copy.flags.writeable = False
                _COPIES.put((leaves[i],), copy)
            host[i] = copy
    rest = sorted(set(range(len(leaves))) - set(wanted))
    for i, x in zip(rest, jax.device_get([leaves[i] for i in rest])):
        host[i] = x
    return jax.tree.unflatten(treedef, host)
