"""The random hash as one GPU kernel call: :mod:`jaxrobo.core.rng`'s Threefry-2x32 through jaxlib's own threefry
kernel, the same bits in a smaller program to compile.

Why: every random draw of a training step (the key split, exploration, the resets) hashes counters with
Threefry-2x32, which :mod:`jaxrobo.core.rng` writes out as about a hundred integer ops that XLA fuses into the step.
On a GPU those ops are a large share of what a run's first use compiles. jaxlib ships the hash as a CUDA kernel
(what JAX itself calls under its ``jax_threefry_gpu_kernel_lowering`` option, "compile times faster at a potential
runtime memory cost"); here each draw calls it. On one H200, an empty cache each run, alternating with the code
before (``benchmarks/results/h200/hash_kernel.json``): the compile of QuadcopterGoto-v2's default run 6.2-7.1 ->
4.1-4.6 s, the arm's 7.9-9.2 -> 6.1-6.2 s, the cart-pole's 1.7-1.9 -> 1.1-1.4 s, a Goto-v2 sweep's 27.2 -> 17.6 s;
from the persistent cache Goto-v2's 0.6 -> 0.5 s. The cost is the kernel's memory traffic: each draw's words go to
memory and back instead of staying in the fused step, so Goto-v2 at 65,536 envs ran 27 % slower (the arm 2 %). So
the execution plan turns it on for the small batches where a run's compile is most of its wall (:data:`MAX_ENVS`),
not for large ones.

Integer arithmetic gives the same bits whichever code computes it: on the H200 the default runs of the three
tabular tasks and the large runs wrote the same bytes with and without it. The kernel is reached with
:func:`jax.ffi.ffi_call` by the custom-call target jaxlib registers it under (``cu_threefry2x32_ffi``), one
:mod:`jax.export` lists among the targets whose behaviour is kept stable across versions; a jaxlib without it
fails the compile, so it is used only on JAX versions in :data:`WRITTEN_FOR` and on CUDA GPUs (elsewhere the
hash's ops, the same values; :func:`unavailable` says why). ``tests/test_hash_kernel.py`` checks the choice, the
lowered call and the fallback; on a GPU the bytes are checked by the benchmark above.

How the choice reaches the hash: like :mod:`jaxrobo.physics.mjx_lean`'s, it travels with tracing
(:meth:`jaxrobo.speed.plan.ExecutionPlan.tracing` enters :func:`choose`; :func:`wanted` reads it).

Public surface: :func:`choose`, :func:`wanted`, :func:`usable`, :func:`unavailable`, :func:`threefry2x32`,
:data:`MAX_ENVS`, :data:`WRITTEN_FOR`, :data:`TARGET`.
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
from typing import Iterator

import jax
import jax.numpy as jnp

from jaxrobo.core.version import outside, warn_once

#: jaxlib's threefry kernel's FFI target on CUDA.
TARGET = "cu_threefry2x32_ffi"
#: JAX versions ``[low, high)`` this was written and tested for (0.10 on CPU: the lowering; 0.11.2 on an H200).
WRITTEN_FOR = ((0, 10), (0, 12))
#: A run's envs on one GPU up to which :meth:`jaxrobo.speed.plan.ExecutionPlan.for_run` calls the kernel: the default
#: runs (2,048-4,096 envs) are mostly compile; at 65,536 Goto-v2's steps ran 27 % slower with it. (Not over several
#: devices: XLA's partitioner cannot split a custom call.)
MAX_ENVS = 8192

_WARNED: set[str] = set()
_CHOICE: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxrobo_hash_kernel", default=False)


@contextlib.contextmanager
def choose(on: bool) -> Iterator[None]:
    """A block whose traces hash with the kernel (``on``, where :func:`usable`) or with the hash's ops; nests, local
    to the thread or task that enters it."""
    if on and not usable():
        warn_once(_WARNED, f"hash_kernel: not used ({unavailable()}); the random hash runs as XLA ops, the same values")
    token = _CHOICE.set(bool(on))
    try:
        yield
    finally:
        _CHOICE.reset(token)


def wanted() -> bool:
    """Whether a trace here hashes with the kernel: chosen (:func:`choose`) and :func:`usable`."""
    return _CHOICE.get() and usable()


@functools.cache
def unavailable() -> str | None:
    """Why the kernel is not used in this process (None: it is): the JAX version, or a backend other than CUDA."""
    reason = outside("jax", jax.__version__, WRITTEN_FOR, "the call to jaxlib's kernel")
    if reason:
        return reason
    if not hasattr(jax, "ffi"):
        return "this JAX has no jax.ffi"
    backend = jax.default_backend()
    if backend != "gpu":
        return f"the backend is {backend}, not a CUDA GPU"
    try:
        from jax.extend.backend import get_backend

        version_text = str(get_backend().platform_version).lower()
    except Exception as err:  # noqa: BLE001 - whatever stops us from asking means: don't use it
        return f"cannot tell the GPU's platform ({err})"
    if "cuda" not in version_text:
        return f"the GPU platform is {version_text!r}, not CUDA"
    return None


def usable() -> bool:
    """Whether this process can call the kernel (:func:`unavailable` gives no reason)."""
    return unavailable() is None


def threefry2x32(k1: jax.Array, k2: jax.Array, x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`jaxrobo.core.rng.threefry2x32` by jaxlib's kernel: the arguments broadcast to one shape (uint32), the
    two words of each counter's hash."""
    args = [jnp.asarray(a, jnp.uint32) for a in (k1, k2, x1, x2)]
    shape = jnp.broadcast_shapes(*(a.shape for a in args))
    if 0 in shape:  # nothing to hash (the kernel is not called with an empty grid)
        zeros = jnp.zeros(shape, jnp.uint32)
        return zeros, zeros
    args = [jnp.broadcast_to(a, shape) for a in args]
    out = jax.ShapeDtypeStruct(shape, jnp.uint32)
    # Elementwise: under vmap every argument gets the batch axis and the kernel hashes the larger array.
    x1, x2 = jax.ffi.ffi_call(TARGET, (out, out), vmap_method="broadcast_all")(*args)
    return x1, x2

