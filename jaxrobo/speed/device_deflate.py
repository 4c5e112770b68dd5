"""A large, mostly-zero device array deflated where it lies: each block's raw deflate bytes and CRC-32 computed on
the device, so that only the compressed bytes cross to the host and no host core deflates them.

Why: a 1 M-env cart-pole run's tables are 8 GB, 93 % zero bytes; made dense and deflated block by block on the
host (zlib-ng, run lengths) they took about 20 CPU seconds, 3.0-3.6 s of an H200 host's 16 cores, and bounded the
run's writing (``docs/writing.md``). A device computes the same kind of stream in a few passes over the array.

The stream: each block of ``block_bytes`` is one deflate block with the fixed Huffman codes (RFC 1951, 3.2.6),
ending with an empty stored block (as zlib's ``Z_SYNC_FLUSH``) so that it ends on a byte and the blocks
concatenate into one stream; :data:`FINAL` ends it. Within a block the array is read as 32-bit words (its bytes in
memory order, little-endian): a nonzero word is its four bytes as literals, a run of zero words one literal zero
then copies of it (distance 1, 258 bytes at most each). Each block's CRC-32 is made of the words' CRCs combined
in a tree (CRC-32 is linear over GF(2): ``crc(a + b)`` is ``crc(a)`` shifted by ``len(b)`` zero bytes, xor
``crc(b)``), with tables from ``zlib_ng.crc32_combine``. Two programs: the first sizes each block (and its CRC),
the second writes them all into one buffer, each block from a 32-bit word of its own.

``zlib`` inflates the stream to the array's bytes (``tests/test_device_deflate.py``); the stream is a pure function
of those bytes and ``block_bytes`` (the same file on any device), not zlib-ng's bytes.

Public surface: :func:`deflate_blocks`, :func:`prepare`, :class:`DeflatedBlocks`, :data:`FINAL`.
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from zlib_ng import zlib_ng as zlib

#: The bytes that end a stream of :func:`deflate_blocks`' blocks: a final, empty block with the fixed codes.
FINAL = b"\x03\x00"
#: The words of this many blocks are encoded at once (their temporaries: under 1 GB at 8 MB blocks on an H200).
GROUP_BLOCKS = 8


class DeflatedBlocks(NamedTuple):
    """The first ``len(crc)`` blocks of ``block_bytes`` of an array, deflated: block ``i``'s raw deflate bytes are
    ``buffer[start[i]:start[i] + size[i]]`` (not final: :data:`FINAL` ends a stream), ``crc[i]`` the CRC-32 of its
    ``block_bytes`` bytes."""

    buffer: np.ndarray
    start: np.ndarray
    size: np.ndarray
    crc: np.ndarray
    block_bytes: int

    def block(self, i: int) -> memoryview:
        return memoryview(self.buffer)[int(self.start[i]):int(self.start[i]) + int(self.size[i])]


def _reversed(code: int, n: int) -> int:
    """Huffman codes go into the stream from their first bit (most significant) on; other fields from their least."""
    return int(format(code, f"0{n}b")[::-1], 2)


@functools.cache
def _codes() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fixed-code bits and bit counts of each literal byte (256) and of each copy of length 0-258 at distance 1
    (lengths under 3 unused): the length's code, its extra bits, then distance code 0 (five zero bits)."""
    lit_val, lit_n = np.zeros(256, np.uint32), np.zeros(256, np.int32)
    for v in range(256):
        code, n = (0x30 + v, 8) if v < 144 else (0x190 + v - 144, 9)
        lit_val[v], lit_n[v] = _reversed(code, n), n
    base = [3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115, 131, 163, 195,
            227, 258]
    extra = [0] * 8 + [1] * 4 + [2] * 4 + [3] * 4 + [4] * 4 + [5] * 4 + [0]
    copy_val, copy_n = np.zeros(259, np.uint32), np.zeros(259, np.int32)
    for length in range(3, 259):
        i = 28 if length == 258 else max(j for j in range(28) if base[j] <= length)
        symbol = 257 + i
        code, n = (symbol - 256, 7) if symbol < 280 else (0xC0 + symbol - 280, 8)
        copy_val[length] = _reversed(code, n) | (length - base[i]) << n
        copy_n[length] = n + extra[i] + 5
    return lit_val, lit_n, copy_val, copy_n


def _shift(crc: int, n: int) -> int:
    """The CRC register ``crc`` after ``n`` zero bytes (without the pre- and post-conditioning)."""
    return zlib.crc32_combine(crc, 0, n)


@functools.cache
def _crc_tables(words: int) -> tuple[np.ndarray, np.ndarray]:
    """``word``: [4, 256] the CRC (unconditioned) of a word's byte ``k`` of value ``v`` followed by its ``3 - k``
    other bytes as zeros; ``levels``: [log2(words), 4, 256], for each level of the tree the shift of a CRC's byte
    ``k`` of value ``v`` by the right half's bytes (4, 8, 16, ... bytes)."""
    one = [zlib.crc32(bytes([v])) ^ zlib.crc32(b"\0") for v in range(256)]
    word = np.array([[_shift(one[v], 3 - k) for v in range(256)] for k in range(4)], np.uint32)
    levels = np.array([[[_shift(v << 8 * k, 4 << level) for v in range(256)] for k in range(4)]
                       for level in range(words.bit_length() - 1)], np.uint32)
    return word, levels


def _by_bytes(table: jax.Array, x: jax.Array) -> jax.Array:
    """``table[0][byte 0 of x] ^ ... ^ table[3][byte 3 of x]`` (a linear map of ``x`` over GF(2), by its bytes)."""
    out = table[0][(x & 0xFF).astype(jnp.int32)]
    for k in range(1, 4):
        out = out ^ table[k][((x >> (8 * k)) & 0xFF).astype(jnp.int32)]
    return out


def _crc0(words: jax.Array, word_table: jax.Array, levels: jax.Array) -> jax.Array:
    """[G] the unconditioned CRC of each row of ``words`` ([G, W], W a power of two)."""
    crc = _by_bytes(word_table, words)
    for level in range(levels.shape[0]):
        pairs = crc.reshape(crc.shape[0], -1, 2)
        crc = _by_bytes(levels[level], pairs[..., 0]) ^ pairs[..., 1]
    return crc.reshape(-1)


def _slots(words: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The bits ([G, 2W] uint32, first bit lowest) and bit counts ([G, 2W] int32) each word of ``words`` ([G, W])
    puts in its block's stream, in two slots a word (at most 26 bits each)."""
    lit_val, lit_n, copy_val, copy_n = (jnp.asarray(t) for t in _codes())
    g, w = words.shape
    index = jnp.arange(w, dtype=jnp.int32)[None, :]
    nonzero = words != 0
    # A zero word's run of zero words: its first word, and the first word after it.
    start = jax.lax.cummax(jnp.where(nonzero, index, -1), axis=1) + 1
    stop = jax.lax.cummin(jnp.where(nonzero, index, w), axis=1, reverse=True)
    t = index - start  # the word's place in its run
    run = 4 * (stop - start)  # bytes
    after = run - 1  # bytes copied after the run's first literal zero
    full, rest = after // 258, after % 258
    # The one emission (after the literal zero) that starts within this word's bytes 4t..4t+3, if any: the i-th at
    # byte 1 + 258 i of the run, i < full a copy of 258, i == full the rest (a copy of 3 or more, or 1-2 literals).
    i = (4 * t + 256) // 258
    here = (1 + 258 * i < 4 * t + 4) & ((i < full) | ((i == full) & (rest > 0)))
    lit0, lit0_n = lit_val[0], lit_n[0]

    def then(first_val: jax.Array, first_n: jax.Array, second_val: jax.Array) -> jax.Array:
        """Bits ``first_val`` (``first_n`` of them) followed by ``second_val``'s."""
        return first_val | (second_val << first_n.astype(jnp.uint32))

    rest_val = jnp.where(rest >= 3, copy_val[rest], jnp.where(rest == 2, then(lit0, lit0_n, lit0), lit0))
    rest_n = jnp.where(rest >= 3, copy_n[rest], rest * lit0_n)
    em_val = jnp.where(here, jnp.where(i < full, copy_val[258], rest_val), jnp.uint32(0))
    em_n = jnp.where(here, jnp.where(i < full, copy_n[258], rest_n), 0)
    first = t == 0
    zero_val = jnp.where(first, then(lit0, lit0_n, em_val), em_val)
    zero_n = jnp.where(first, lit0_n, 0) + em_n
    b = [((words >> (8 * k)) & 0xFF).astype(jnp.int32) for k in range(4)]
    val_a = jnp.where(nonzero, then(lit_val[b[0]], lit_n[b[0]], lit_val[b[1]]), zero_val)
    n_a = jnp.where(nonzero, lit_n[b[0]] + lit_n[b[1]], zero_n)
    val_b = jnp.where(nonzero, then(lit_val[b[2]], lit_n[b[2]], lit_val[b[3]]), jnp.uint32(0))
    n_b = jnp.where(nonzero, lit_n[b[2]] + lit_n[b[3]], 0)
    vals = jnp.stack([val_a, val_b], axis=-1).reshape(g, 2 * w).astype(jnp.uint32)
    counts = jnp.stack([n_a, n_b], axis=-1).reshape(g, 2 * w).astype(jnp.int32)
    return vals, counts


#: Bits before a block's first symbol (the header: not final, fixed codes) and after its last (the end-of-block
#: code, then the empty stored block's header); then the stream is padded to a byte and takes 00 00 FF FF.
_HEAD_BITS, _TAIL_BITS = 3, 7 + 3


def _sizes_of(counts: jax.Array) -> jax.Array:
    """[G] each block's bytes: its header, symbols, end and empty stored block."""
    bits = _HEAD_BITS + counts.sum(axis=1) + _TAIL_BITS
    return (bits + 7) // 8 + 4


def _words(x: jax.Array, blocks: int, w: int) -> jax.Array:
    """The first ``blocks`` blocks of ``x``'s bytes as [blocks, w] 32-bit words."""
    flat = x.reshape(-1)
    if flat.dtype == jnp.bool_:  # one byte each, 0 or 1 (bitcasts do not take bool)
        flat = flat.astype(jnp.uint8)
    size = flat.dtype.itemsize
    flat = flat[:blocks * w * 4 // size]
    if size == 4:
        words = jax.lax.bitcast_convert_type(flat, jnp.uint32)
    else:
        narrow = jax.lax.bitcast_convert_type(flat, jnp.dtype(f"uint{8 * size}"))
        words = jax.lax.bitcast_convert_type(narrow.reshape(-1, 4 // size), jnp.uint32)
    return words.reshape(blocks, w)


def _group_starts(blocks: int, group: int) -> np.ndarray:
    """The first block of each group of ``group`` blocks (all of them where there are fewer): the last group ends
    at the last block, so it may take blocks of the group before it again (the array is never padded: at 1 M envs
    a padded copy would be 8 GB more of the device's memory)."""
    size = min(group, blocks)
    return np.minimum(np.arange(0, blocks, size), blocks - size).astype(np.int32)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _measure(x: jax.Array, blocks: int, w: int, group: int, group_starts: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[groups, group] the deflated size (bytes) and unconditioned CRC of each group's blocks
    (:func:`_group_starts`)."""
    word_table, levels = (jnp.asarray(t) for t in _crc_tables(w))
    words = _words(x, blocks, w)
    size = min(group, blocks)

    def one(first: jax.Array) -> tuple[jax.Array, jax.Array]:
        group = jax.lax.dynamic_slice_in_dim(words, first, size, axis=0)
        _, counts = _slots(group)
        return _sizes_of(counts), _crc0(group, word_table, levels)

    return jax.lax.map(one, group_starts)


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4))
def _write(x: jax.Array, blocks: int, w: int, group: int, capacity: int, group_starts: jax.Array,
           first_word: jax.Array, sizes: jax.Array) -> jax.Array:
    """[capacity] 32-bit words holding the first ``blocks`` blocks' streams, block ``i`` from word
    ``first_word[i]`` on (``sizes[i]`` bytes)."""
    words = _words(x, blocks, w)
    size = min(group, blocks)

    def add(out: jax.Array, word: jax.Array, bit: jax.Array, val: jax.Array, n: jax.Array) -> jax.Array:
        """``val`` (``n`` bits, at most 26) put at bit ``bit`` of the stream that starts at word ``word``."""
        at = word + (bit >> 5)
        shift = (bit & 31).astype(jnp.uint32)
        low = val << shift
        high = jnp.where(shift == 0, jnp.uint32(0), val >> (jnp.uint32(32) - shift))
        spill = (n > 0) & (high != 0)
        out = out.at[jnp.where(n > 0, at, capacity).reshape(-1)].add(low.reshape(-1), mode="drop")
        return out.at[jnp.where(spill, at + 1, capacity).reshape(-1)].add(high.reshape(-1), mode="drop")

    def one(g: jax.Array, out: jax.Array) -> jax.Array:
        first = group_starts[g]
        vals, counts = _slots(jax.lax.dynamic_slice_in_dim(words, first, size, axis=0))
        bits = jnp.cumsum(counts, axis=1) - counts + _HEAD_BITS
        index = first + jnp.arange(size, dtype=jnp.int32)
        # Blocks the group before this one took already (the last group only) are not written twice.
        start = jnp.where(index >= g * size, first_word[index], capacity)
        return add(out, start[:, None], bits, vals, counts)

    out = jax.lax.fori_loop(0, group_starts.shape[0], one, jnp.zeros(capacity, jnp.uint32))
    head = jnp.full(blocks, 2, jnp.uint32)  # bit 0: not final; bits 1-2: 01, the fixed codes
    out = add(out, first_word, jnp.zeros(blocks, jnp.int32), head, jnp.full(blocks, 3))
    return add(out, first_word, 8 * (sizes - 2), jnp.full(blocks, 0xFFFF, jnp.uint32), jnp.full(blocks, 16))


def _rounded_words(n: int) -> int:
    """``n`` rounded up to one of 16 sizes an octave (at least 1,024), so that runs of other sizes reuse the
    writing program."""
    step = 1 << max(10, n.bit_length() - 4)
    return max(step, -(-n // step) * step)


def prepare(like: jax.ShapeDtypeStruct, block_bytes: int, *, group: int = GROUP_BLOCKS) -> None:
    """Compile the program that sizes the blocks of an array shaped as ``like`` (the other one's shape depends on
    those sizes): a later :func:`deflate_blocks` on such an array runs it at once."""
    blocks = like.size * np.dtype(like.dtype).itemsize // block_bytes
    if blocks:
        starts = _group_starts(blocks, group)
        _measure.lower(like, blocks, block_bytes // 4, group,
                       jax.ShapeDtypeStruct(starts.shape, starts.dtype)).compile()


def deflate_blocks(x: jax.Array, block_bytes: int, *, get: Any = jax.device_get,
                   group: int = GROUP_BLOCKS) -> DeflatedBlocks | None:
    """The whole blocks of ``block_bytes`` of ``x``'s bytes (C order), each deflated on ``x``'s device; None where
    there is none, or where ``block_bytes`` is not a power of two of 8 bytes or more or ``x``'s items are not 1, 2
    or 4 bytes. ``get``: how the buffer crosses to the host (``jaxrobo.speed.locked_copy.get`` on a GPU);
    ``group``: blocks encoded at once (the stream is the same for any)."""
    size = np.dtype(x.dtype).itemsize
    w = block_bytes // 4
    blocks = x.nbytes // block_bytes
    if blocks == 0 or size not in (1, 2, 4) or block_bytes < 8 or block_bytes & (block_bytes - 1):
        return None
    starts = _group_starts(blocks, group)
    by_group = jax.device_get(_measure(x, blocks, w, group, jnp.asarray(starts)))
    sizes, crc0 = np.zeros(blocks, np.int64), np.zeros(blocks, np.uint32)
    index = starts[:, None] + np.arange(min(group, blocks))
    sizes[index], crc0[index] = by_group
    first = np.concatenate([[0], np.cumsum(-(-sizes // 4))])
    if first[-1] >= 2 ** 31 - 1:
        return None
    capacity = _rounded_words(int(first[-1]))
    buffer = get(_write(x, blocks, w, group, capacity, jnp.asarray(starts), jnp.asarray(first[:-1], jnp.int32),
                        jnp.asarray(sizes, jnp.int32)))
    zeros = zlib.crc32(bytes(block_bytes))
    crc = np.asarray(crc0, np.uint32) ^ np.uint32(zeros)
    return DeflatedBlocks(np.asarray(buffer).view(np.uint8), first[:-1] * 4, sizes, crc.astype(np.int64), block_bytes)
