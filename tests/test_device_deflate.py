"""jaxrobo.speed.device_deflate: each block's stream inflates (zlib) to the array's bytes and its CRC-32 is zlib's, for
every kind of run of zeros, item size and grouping; arrays it does not take give None."""
from __future__ import annotations

import logging
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.speed import device_deflate as dd


def _check(a: np.ndarray, block: int, **kw) -> dd.DeflatedBlocks:
    """``a``'s whole blocks deflated on the device: one stream (with FINAL) inflating to their bytes, each CRC
    zlib's, each block a stream of its own once ended."""
    d = dd.deflate_blocks(jnp.asarray(a), block, **kw)
    raw = np.ascontiguousarray(a).reshape(-1).view(np.uint8)
    n = a.nbytes // block
    assert d is not None and len(d.crc) == n == len(d.size) == len(d.start) and d.block_bytes == block
    stream = b"".join(bytes(d.block(i)) for i in range(n)) + dd.FINAL
    assert zlib.decompressobj(-15).decompress(stream) == raw[:n * block].tobytes()
    assert [int(c) for c in d.crc] == [zlib.crc32(raw[i * block:(i + 1) * block]) for i in range(n)]
    for i in range(n):
        alone = zlib.decompressobj(-15).decompress(bytes(d.block(i)) + dd.FINAL)
        assert alone == raw[i * block:(i + 1) * block].tobytes()
    return d


def test_sparse_tables_several_blocks_and_a_last_one_cut_short():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(37, 480, 4)).astype(np.float32)
    a[rng.random(a.shape) < 0.93] = 0
    a.reshape(-1)[:3] = -0.0  # nonzero bits, zero value: literals
    d = _check(a, 4096)
    assert d.size.sum() < 0.2 * len(d.crc) * 4096


@pytest.mark.parametrize("words", [1, 2, 64, 65, 129, 130, 200, 1033])
def test_every_run_of_zeros(words):
    """Runs of zero words whose bytes after the first need 258-byte copies and a rest of 1 byte or of 3 or more,
    at the block's start, middle and end."""
    a = np.ones(4096, np.float32)
    a[7:7 + words] = 0
    a[:min(words, 5)] = 0
    a[-words:] = 0
    _check(a, 4096)
    _check(np.zeros(2048, np.float32), 4096)  # a block of zeros only


def test_dense_words_every_byte_value_and_narrow_items():
    rng = np.random.default_rng(1)
    _check(rng.integers(0, 2 ** 32, size=4096, dtype=np.uint32).view(np.float32), 4096)  # bytes 0-255, 8 and 9 bits
    _check(rng.integers(-2, 3, size=3 * 4096).astype(np.int8), 4096)
    _check(rng.integers(0, 3, size=2 * 4096).astype(np.int16), 2048)
    _check((rng.random(4096) < 0.5).astype(np.bool_), 1024)


@pytest.mark.parametrize("group", [1, 2, 3, 8])
def test_the_stream_is_the_same_whatever_the_grouping(group):
    """5 blocks in groups of 2 (or 3): the last group takes blocks of the one before again, written once."""
    rng = np.random.default_rng(2)
    a = rng.normal(size=5 * 1024).astype(np.float32)
    a[rng.random(a.size) < 0.9] = 0
    base = _check(a, 4096, group=8)
    d = _check(a, 4096, group=group)
    assert all(bytes(d.block(i)) == bytes(base.block(i)) for i in range(5)) and list(d.crc) == list(base.crc)


def test_arrays_it_does_not_take():
    assert dd.deflate_blocks(jnp.zeros(100, jnp.float32), 4096) is None  # no whole block
    assert dd.deflate_blocks(jnp.zeros(3000, jnp.float32), 3000) is None  # not a power of two
    assert dd.deflate_blocks(jnp.zeros(1024, jnp.float32), 4) is None  # under 8 bytes


def test_prepare_compiles_what_the_call_runs(caplog):
    a = np.zeros((4, 1024), np.float32)
    a[1, 5] = 3.0
    x = jax.device_put(jnp.asarray(a), jax.devices()[0])
    dd.prepare(jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), 4096, group=2)
    with jax.log_compiles(True), caplog.at_level(logging.DEBUG):
        d = dd.deflate_blocks(x, 4096, group=2)
    compiled = " ".join(r.getMessage() for r in caplog.records if "ompil" in r.getMessage())
    assert "_write" in compiled and "_measure" not in compiled  # the call found the program prepare compiled
    assert zlib.decompressobj(-15).decompress(b"".join(bytes(d.block(i)) for i in range(4)) + dd.FINAL) == a.tobytes()
