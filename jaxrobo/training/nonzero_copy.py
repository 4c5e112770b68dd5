"""A device array's host copy made from its nonzero entries: which entries are nonzero (a bit each) and their values
cross to the host, the zeros are made there.

Why: a run's per-env Q-tables are mostly unvisited entries, still zero (1 M cart-pole envs stopped at their target:
8 GB, 93 % zero bytes), and the copy to the host was the largest part of a big run's end: an H200 host copied
into fresh host memory at 0.8-1.5 GB/s however the copy was issued (``benchmarks/results/h200/run_end_ab_s15.json``),
so 4.7 s of the tables alone at 1 M envs, 0.5 s at 65,536. Here two small programs run on the device: one packs
the mask (entries whose bits are not all zero, so ``-0.0`` is kept as it is) and counts the nonzero entries of each
block of :data:`jaxrobo.io.npz.BLOCK_BYTES`; the other gathers those entries' bits in order into an array sized
to their count (rounded up to one of 16 sizes an octave, so that runs of other counts reuse its compiled program).
About a bit and a tenth of an entry's bytes cross instead of the entry. On a CUDA GPU the mask and the values cross
through page-locked memory (:mod:`jaxrobo.speed.locked_copy`); the whole tables copied that way instead wrote a
1 M-env run no faster and held 7 GB more host memory (``benchmarks/results/h200/locked_copy_s34.json``).

The host copy (:class:`NonzeroCopy`) is made dense only where it is read: :meth:`NonzeroCopy.dense` (a thread
per core, block by block), or block by block by the ``.npz`` writer (:func:`jaxrobo.io.npz.write_npz_deflated`
takes it as an array), whose file is the same bytes as the dense array's. The same array copied again (the
closing checkpoint's thread, then the run's result) gives the same copy while the array lives: its bytes cross once.

Used on accelerators only, for arrays on one device of :data:`FROM_BYTES` or more with at most :data:`MAX_SHARE` of
their entries nonzero (otherwise the plain copy, a numpy array: on CPUs the array is host memory already; an array
split over devices would need the programs' collectives, issued from the checkpoint's thread beside the run's).
The values are the array's bit for bit either way.

For the tables' file, :func:`file_copy` also deflates a large copy's blocks on the device
(:mod:`jaxrobo.speed.device_deflate`), after the shared copy is made; :func:`prepare` compiles what that runs from
the carry's shapes while the run compiles.

Public surface: :func:`host_copy`, :func:`file_copy`, :func:`prepare`, :class:`NonzeroCopy`, :data:`FROM_BYTES`,
:data:`MAX_SHARE`, :data:`DEFLATE_FROM_BYTES`.
"""
from __future__ import annotations

import functools
import threading
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core.environ import in_threads, usable_cores
from jaxrobo.core.memo import IdentityMemo
from jaxrobo.speed import device_deflate, locked_copy

#: Arrays smaller than this cross whole (the two programs and their reads cost more than they save).
FROM_BYTES = 64 << 20
#: Arrays with more than this share of nonzero entries cross whole (mask and values would be most of their bytes).
MAX_SHARE = 0.75
#: Arrays of this many bytes or more are also deflated on the device for their file (:func:`file_copy`): at 1 M
#: envs (8 GB of tables) an H200 host's run wrote in 2.9-3.2 s instead of 4.7-5.0 s; at 65,536 envs (0.5 GB) its 16
#: cores deflated as fast (0.6-0.8 s either way) and compiling the programs ahead took 0.3 s of the compile
#: (``benchmarks/results/h200/device_deflate_s35.json``).
DEFLATE_FROM_BYTES = 1 << 30


class NonzeroCopy:
    """A host copy of an array as the mask of its nonzero entries (``bits``: packed, ``np.packbits`` order over the
    flat C-ordered entries) and their bit patterns in order (``values``, padded at the end), with the count of
    nonzero entries in each block of ``block`` entries (``counts``). Shaped like the array (``shape``, ``dtype``,
    ``ndim``, ``nbytes``, ``size``; :meth:`reshape`); :meth:`dense` makes the array, :meth:`npy_pieces` its bytes
    block by block for the ``.npz`` writer."""

    def __init__(self, shape: tuple[int, ...], dtype: Any, bits: np.ndarray, values: np.ndarray, counts: np.ndarray,
                 block: int, deflated: device_deflate.DeflatedBlocks | None = None) -> None:
        self.shape, self.dtype, self.block = tuple(int(n) for n in shape), np.dtype(dtype), int(block)
        self.bits, self.values, self.deflated = bits, values, deflated
        self.counts = np.asarray(counts, np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])  # where each block's values start

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def reshape(self, *shape: Any) -> "NonzeroCopy":
        """The same entries under another shape (C order, as ``np.reshape``)."""
        shape = tuple(shape[0]) if len(shape) == 1 and isinstance(shape[0], (tuple, list)) else shape
        if int(np.prod(shape, dtype=np.int64)) != self.size:
            raise ValueError(f"cannot reshape {self.shape} into {shape}")
        return NonzeroCopy(shape, self.dtype, self.bits, self.values, self.counts, self.block, self.deflated)

    def with_deflated(self, deflated: device_deflate.DeflatedBlocks | None) -> "NonzeroCopy":
        """The same entries, with the whole blocks' streams ``deflated`` (:func:`file_copy`)."""
        return NonzeroCopy(self.shape, self.dtype, self.bits, self.values, self.counts, self.block, deflated)

    def __getitem__(self, index: Any) -> "NonzeroCopy":
        """Only ``copy[None]`` (a leading axis of one, as a shared table is given in ``qtables.npz``)."""
        if index is None:
            return self.reshape((1, *self.shape))
        raise TypeError("a NonzeroCopy is indexed only by None; take .dense() first")

    def fill(self, out: np.ndarray, start: int, stop: int) -> None:
        """Entries ``start:stop`` into ``out`` (their length): a block, ``start`` a multiple of ``block`` and ``stop``
        the next one or the end."""
        word = np.dtype(f"u{self.dtype.itemsize}")
        k = start // self.block
        mask = np.unpackbits(self.bits[start // 8:-(-stop // 8)], count=stop - start).view(bool)
        target = out.view(word)
        target[...] = 0
        target[mask] = self.values[self.offsets[k]:self.offsets[k + 1]]

    def dense(self) -> np.ndarray:
        """The array (a thread per core, a block each at a time)."""
        out = np.empty(self.size, self.dtype)
        starts = list(range(0, self.size, self.block))
        stops = [min(s + self.block, self.size) for s in starts]
        in_threads(lambda a, b: self.fill(out[a:b], a, b), starts, stops,
                   threads=1 if len(starts) < 2 else usable_cores(), name="jaxrobo-dense")
        return out.reshape(self.shape)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = self.dense()
        return out if dtype is None else out.astype(dtype)

    def npy_pieces(self, block_bytes: int) -> list["_Piece"]:
        """The array's C-ordered bytes in pieces of ``block_bytes`` (which must be ``block`` entries), each made
        when the writer's thread takes it; those deflated on the device (:attr:`deflated`) also give their stream."""
        if block_bytes != self.block * self.dtype.itemsize:
            raise ValueError(f"pieces of {block_bytes} bytes asked of a copy counted in blocks of {self.block} "
                             "entries")
        ready = self.deflated if self.deflated is not None and self.deflated.block_bytes == block_bytes else None
        return [_Piece(self, s, min(s + self.block, self.size), ready if ready is not None and k < len(ready.crc)
                       else None) for k, s in enumerate(range(0, self.size, self.block))]


class _Piece:
    """Entries ``start:stop`` of a :class:`NonzeroCopy`, as bytes made when :meth:`view` is called; where the block
    was deflated on the device, its stream too (:meth:`deflated`)."""

    def __init__(self, copy: NonzeroCopy, start: int, stop: int,
                 ready: device_deflate.DeflatedBlocks | None = None) -> None:
        self.copy, self.start, self.stop = copy, start, stop
        self.nbytes = (stop - start) * copy.dtype.itemsize
        if ready is not None:
            self.deflated = functools.partial(_deflated, ready, start // copy.block)

    def view(self) -> memoryview:
        out = np.empty(self.stop - self.start, self.copy.dtype)
        self.copy.fill(out, self.start, self.stop)
        return memoryview(out.view(np.uint8))


def _deflated(ready: device_deflate.DeflatedBlocks, k: int, last: bool) -> tuple[bytes | memoryview, int]:
    """Block ``k``'s raw deflate bytes (ending the stream where ``last``) and the CRC-32 of its bytes."""
    block = ready.block(k)
    return (bytes(block) + device_deflate.FINAL if last else block), int(ready.crc[k])


def _word(dtype: Any) -> Any:
    return jnp.dtype(f"uint{8 * jnp.dtype(dtype).itemsize}")


@functools.partial(jax.jit, static_argnums=1)
def _mask(x: jax.Array, block: int) -> tuple[jax.Array, jax.Array]:
    """The packed mask of ``x``'s nonzero entries (bits not all zero) and their count per block of entries."""
    nonzero = jax.lax.bitcast_convert_type(x, _word(x.dtype)).reshape(-1) != 0
    pad = -nonzero.size % block
    counts = jnp.pad(nonzero, (0, pad)).reshape(-1, block).sum(axis=1, dtype=jnp.int32)
    return jnp.packbits(nonzero), counts


@functools.partial(jax.jit, static_argnums=1)
def _gather(x: jax.Array, cap: int) -> jax.Array:
    """The bits of ``x``'s nonzero entries in order, in an array of ``cap`` (at least their count)."""
    bits = jax.lax.bitcast_convert_type(x, _word(x.dtype)).reshape(-1)
    nonzero = bits != 0
    at = jnp.where(nonzero, jnp.cumsum(nonzero, dtype=jnp.int32) - 1, cap)
    return jnp.zeros(cap, bits.dtype).at[at].set(bits, mode="drop")


def _rounded(count: int) -> int:
    """``count`` rounded up to one of 16 sizes an octave (at least 1,024)."""
    step = 1 << max(10, count.bit_length() - 4)
    return max(step, -(-count // step) * step)


def file_copy(x: Any, *, deflate_from: int | None = None) -> np.ndarray | NonzeroCopy:
    """:func:`host_copy`'s copy of ``x`` for a file: where it is a :class:`NonzeroCopy` of ``deflate_from`` bytes
    or more (default :data:`DEFLATE_FROM_BYTES`), its whole blocks are also deflated on ``x``'s device
    (:mod:`jaxrobo.speed.device_deflate`; :attr:`NonzeroCopy.deflated`, which the ``.npz`` writer takes as they
    are), after the copy that :func:`host_copy` hands to other callers (a run's result) is made. Where the
    programs' temporaries do not fit beside the run's arrays, the writer deflates the blocks on the host."""
    from jaxrobo.io import npz

    copy = host_copy(x)
    smallest = DEFLATE_FROM_BYTES if deflate_from is None else deflate_from
    if not isinstance(copy, NonzeroCopy) or copy.nbytes < smallest:
        return copy
    try:
        ready = device_deflate.deflate_blocks(x, npz.BLOCK_BYTES, get=locked_copy.get)
    except RuntimeError:
        return copy
    return copy if ready is None else copy.with_deflated(ready)


def _taken(x: Any, devices: Any, from_bytes: int, *, on_cpu: bool, itemsizes: tuple[int, ...]) -> bool:
    """Whether an array shaped as ``x`` on ``devices`` crosses by this module's programs: one device, an accelerator
    (or a CPU, ``on_cpu``), ``from_bytes`` or more, items of ``itemsizes`` bytes, the writer's blocks a whole number
    of its entries and of mask bytes."""
    from jaxrobo.io import npz

    itemsize = np.dtype(x.dtype).itemsize
    block = npz.BLOCK_BYTES // itemsize
    return len(devices) == 1 and (on_cpu or {d.platform for d in devices} != {"cpu"}) and itemsize in itemsizes \
        and 0 < x.size * itemsize and x.size * itemsize >= from_bytes and block >= 8 and block % 8 == 0 \
        and block * itemsize == npz.BLOCK_BYTES


def prepare(x: Any, *, deflate_from: int | None = None) -> list[threading.Thread]:
    """Compile, in a thread, the programs :func:`file_copy` runs on an array shaped as ``x`` (an array or a
    ``jax.ShapeDtypeStruct`` on one accelerator, the default device where it names none) whose shapes alone
    decide (the mask's and the blocks' sizes and CRCs): a run's end then runs them at once (at 1 M envs their
    traces and reads from the compilation cache took 0.5 and 0.7 s there, on an H200 host). The thread is
    returned (not a daemon's: the caller joins it); none where the array would cross whole or not be deflated there
    (``deflate_from``, as :func:`file_copy`'s). A failure is left to the programs' own calls."""
    from jaxrobo.io import npz

    sharding = getattr(x, "sharding", None)
    if sharding is None:
        sharding = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    smallest = max(FROM_BYTES, DEFLATE_FROM_BYTES if deflate_from is None else deflate_from)
    if not _taken(x, sharding.device_set, smallest, on_cpu=False, itemsizes=(1, 2, 4)):
        return []
    block = npz.BLOCK_BYTES // np.dtype(x.dtype).itemsize
    like = jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)

    def compile_both() -> None:
        try:
            _mask.lower(like, block).compile()
            device_deflate.prepare(like, npz.BLOCK_BYTES)
        except Exception:  # noqa: BLE001 - the calls themselves compile again and raise where they are made
            pass

    thread = threading.Thread(target=compile_both, name="jaxrobo-compile-copy")
    thread.start()
    return [thread]


#: The latest array's copy only: a run's tables, copied by its checkpoint and for its result.
_COPIES = IdentityMemo(latest_only=True)


def host_copy(x: Any, *, from_bytes: int | None = None, on_cpu: bool = False) -> np.ndarray | NonzeroCopy:
    """``x`` on the host: a :class:`NonzeroCopy` where it is an accelerator array on one device of ``from_bytes``
    (default :data:`FROM_BYTES`) or more with at most :data:`MAX_SHARE` of its entries nonzero, else the plain
    copy (``np.asarray(jax.device_get(x))``). ``on_cpu``: a CPU array too (tests). The same array asked for again
    while it lives (by another thread too) gives the same copy, made once."""
    from jaxrobo.io import npz

    if not isinstance(x, jax.Array) or not _taken(x, x.devices(), FROM_BYTES if from_bytes is None else from_bytes,
                                                  on_cpu=on_cpu, itemsizes=(1, 2, 4, 8)):
        return np.asarray(jax.device_get(x))
    block = npz.BLOCK_BYTES // np.dtype(x.dtype).itemsize  # the writer's blocks, each a whole number of mask bytes

    def make() -> np.ndarray | NonzeroCopy:
        try:
            bits, counts = locked_copy.get(_mask(x, block))
            total = int(np.asarray(counts, np.int64).sum())
            if total <= MAX_SHARE * x.size and total < 2 ** 31 - 1:
                values = np.asarray(locked_copy.get(_gather(x, _rounded(total))))
                return NonzeroCopy(x.shape, x.dtype, np.asarray(bits), values, counts, block)
        except RuntimeError:  # the programs' temporaries did not fit beside the run's arrays: the plain copy
            pass
        return np.asarray(locked_copy.get(x))

    return _COPIES.get_or_make((x,), make)
