"""``.npz`` files read back as hostile input: every array's header is checked before its data is read.

A checkpoint or a q-table file may be truncated, bit-flipped, pickled, or claim an array of 2^40 rows in its
header; ``np.load`` would raise one of half a dozen exceptions or try to allocate terabytes. :func:`read_npz`
reads each member's ``.npy`` header with :mod:`numpy.lib.format` first (dtype, shape, and the bytes they need
against a cap and against the member's own size in the zip), compares it with an expected template when one
is given, then reads the data (the zip's CRC checks it) and refuses non-finite float arrays. Every failure is
one :class:`NpzError` (a :class:`~jaxrobo.core.config.ConfigError`) naming the file and the array.
"""
from __future__ import annotations

import contextlib
import errno
import io
import math
import mmap
import os
import zipfile
import zlib
from typing import IO, Any, Mapping

import numpy as np

from jaxrobo.core.config import ConfigError

#: Largest array (bytes) read from a file by default: a run's tables and carry are far below it.
MAX_ARRAY_BYTES = 16 << 30


class NpzError(ConfigError):
    """An ``.npz`` file that cannot be used: unreadable, or not holding the arrays expected."""


#: Arrays above this size are stored in an ``.npz`` uncompressed (:func:`write_npz_deflated`).
STORE_ABOVE_BYTES = 32 << 20


def write_npz_deflated(path: str | IO[bytes], *, store_above: int = STORE_ABOVE_BYTES, **arrays: Any) -> None:
    """``arrays`` to ``path`` (a file name, or a binary file open for writing) as an ``.npz`` that ``np.load``
    reads like ``np.savez_compressed``'s: each array up to ``store_above`` bytes (default
    :data:`STORE_ABOVE_BYTES`; -1: none, the layout of ``np.savez``) deflated at level 1 (nearly as small as zlib's
    default level in about half the time), each larger one stored as it is. Writing is part of every ``jaxrobo
    train``'s wall: 65,536 per-env cart-pole tables (0.5 GB) took tens of seconds to deflate on 2 CPU cores, and
    under a second to store. Where the stored arrays are :data:`UNCACHED_ABOVE_BYTES` or more, the file goes
    through :class:`UncachedWrites` (where the file system allows it)."""
    arrays = {name: np.asanyarray(value) for name, value in arrays.items()}
    stored = sum(x.nbytes for x in arrays.values() if x.nbytes > store_above)
    with contextlib.ExitStack() as stack:
        if stored >= UNCACHED_ABOVE_BYTES:
            f = stack.enter_context(open(path, "wb")) if isinstance(path, (str, os.PathLike)) else path
            try:
                path = stack.enter_context(UncachedWrites(f))
            except OSError:  # no O_DIRECT here (tmpfs, some network file systems): the page cache, as usual
                path = f
        zf = stack.enter_context(zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1,
                                                 allowZip64=True))
        for name, value in arrays.items():
            member: str | zipfile.ZipInfo = f"{name}.npy"  # a name takes the file's compression (deflate, level 1)
            if value.nbytes > store_above:
                member = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                member.compress_type = zipfile.ZIP_STORED
            with zf.open(member, "w", force_zip64=True) as f:
                write_array(f, value)


#: Stored arrays of at least this many bytes in all are written past the page cache (:class:`UncachedWrites`).
UNCACHED_ABOVE_BYTES = 64 << 20


class UncachedWrites(io.RawIOBase):
    """A binary file open for writing (``f``, at its position), written with ``O_DIRECT`` where a write is large:
    its 4096-byte-aligned middle goes from an aligned buffer straight to the disk, the unaligned ends (and every
    small write: zip headers) through ``f``'s descriptor and the page cache as usual. Every write is positional;
    ``f``'s own buffer is not used (close this before using ``f`` again; its ``fsync`` covers both).

    Why: a file of hundreds of MB written through the page cache needs as many fresh pages, which on a virtual
    machine that hands its free memory back to the host cost several times the writing (a 0.5 GB checkpoint:
    seconds, where the same bytes written with ``O_DIRECT`` took a fraction of one, already on the disk). Opening
    ``O_DIRECT`` raises OSError where the file system does not have it."""

    ALIGN = 4096
    #: Writes of at least this many bytes take the direct path.
    DIRECT_FROM = 1 << 20

    def __init__(self, f: IO[bytes]) -> None:
        super().__init__()
        f.flush()
        self._fd, self._pos = f.fileno(), f.tell()
        if not hasattr(os, "O_DIRECT"):
            raise OSError("no O_DIRECT on this system")
        self._direct = os.open(f"/proc/self/fd/{self._fd}", os.O_WRONLY | os.O_DIRECT)
        self._direct_ok = True  # until a direct write is refused (EINVAL): the rest then go through the page cache
        # Page-aligned, reused for every direct write; a whole number of aligned blocks.
        self._buffer = mmap.mmap(-1, max(self.ALIGN, WRITE_CHUNK_BYTES // self.ALIGN * self.ALIGN))
        self._aligned = np.frombuffer(self._buffer, np.uint8)  # copied into by numpy, without the GIL

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: os.fstat(self._fd).st_size}[whence]
        self._pos = base + offset
        return self._pos

    def _pwrite(self, fd: int, data: memoryview, offset: int) -> None:
        while data.nbytes:
            n = os.pwrite(fd, data, offset)
            data, offset = data[n:], offset + n

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        n, pos = view.nbytes, self._pos
        head = (-pos) % self.ALIGN
        middle = (n - head) // self.ALIGN * self.ALIGN if n >= self.DIRECT_FROM and self._direct_ok else 0
        if middle <= 0:
            self._pwrite(self._fd, view, pos)
        else:
            self._pwrite(self._fd, view[:head], pos)
            for start in range(head, head + middle, len(self._buffer)):
                k = min(len(self._buffer), head + middle - start)
                if self._direct_ok:
                    np.copyto(self._aligned[:k], np.frombuffer(view[start:start + k], np.uint8))
                    try:
                        self._pwrite(self._direct, memoryview(self._buffer)[:k], pos + start)
                        continue
                    except OSError as err:  # a device whose blocks are not 4096-aligned: the page cache from here
                        if err.errno != errno.EINVAL:
                            raise
                        self._direct_ok = False
                self._pwrite(self._fd, view[start:start + k], pos + start)
            self._pwrite(self._fd, view[head + middle:], pos + head + middle)
        self._pos = pos + n
        return n

    def close(self) -> None:
        if not self.closed:
            os.close(self._direct)
            del self._aligned  # the buffer's only export: it closes then
            self._buffer.close()
        super().close()


#: Bytes handed to a zip member per write (:func:`write_array`): each is checksummed and written in turn.
WRITE_CHUNK_BYTES = 16 << 20


def write_array(f: IO[bytes], value: np.ndarray) -> None:
    """``value`` to ``f`` as the ``.npy`` bytes ``np.lib.format.write_array(f, value, allow_pickle=False)`` writes,
    without its copies: numpy copies every 16 MB of an array into a new ``bytes`` object before writing it to a
    file object that is not a real file (a zip member), and at hundreds of MB those fresh pages cost more than the
    writing. A C-contiguous array is written from its own memory; any other through one reused buffer, a block of
    rows at a time."""
    fmt = np.lib.format
    if value.dtype.hasobject or (value.flags.f_contiguous and not value.flags.c_contiguous):
        fmt.write_array(f, value, allow_pickle=False)  # refuses objects; keeps a Fortran array's own layout
        return
    fmt.write_array_header_1_0(f, fmt.header_data_from_array_1_0(value))
    if value.flags.c_contiguous:
        flat = value.reshape(-1).view(np.uint8)
        for start in range(0, flat.size, WRITE_CHUNK_BYTES):
            f.write(flat[start:start + WRITE_CHUNK_BYTES])
        return
    rows = max(1, WRITE_CHUNK_BYTES // max(1, value[:1].nbytes))
    buffer = np.empty((min(rows, value.shape[0]),) + value.shape[1:], value.dtype)
    for start in range(0, value.shape[0], rows):
        block = buffer[:min(rows, value.shape[0] - start)]
        np.copyto(block, value[start:start + block.shape[0]])
        f.write(block.reshape(-1).view(np.uint8))


def _header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype]:
    from numpy.lib import format as npy

    with zf.open(info) as f:
        version = npy.read_magic(f)
        reader = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}.get(tuple(version))
        if reader is None:
            raise ValueError(f"unknown .npy format version {version}")
        shape, _fortran, dtype = reader(f)
    return tuple(int(n) for n in shape), np.dtype(dtype)


def read_npz(path: str, what: str = "the file", *, expect: Mapping[str, tuple[tuple[int, ...], Any]] | None = None,
             finite: bool | Mapping[str, bool] = True, max_bytes: int = MAX_ARRAY_BYTES) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, checked before and after reading (see the module).

    ``expect``: ``{name: (shape, dtype)}`` the arrays must have (a name missing from the file is an error; names
    not in ``expect`` are read too, under ``max_bytes``). ``finite``: refuse float arrays holding NaN or inf (all,
    or per name). Raises :class:`NpzError` naming ``what``, the file and the array."""
    where = f"{path}: {what}"
    from jaxrobo.core.config import check_regular

    check_regular(path, where)  # a FIFO would hang the read, a device never end it
    try:
        with zipfile.ZipFile(path) as zf:
            infos = {i.filename[:-4] if i.filename.endswith(".npy") else i.filename: i for i in zf.infolist()}
            headers = {}
            for name, info in infos.items():
                try:
                    shape, dtype = _header(zf, info)
                except (ValueError, SyntaxError, TypeError, OverflowError) as err:
                    raise NpzError(f"{where}: array {name!r} has no valid .npy header ({err})") from None
                if any(n < 0 for n in shape):
                    raise NpzError(f"{where}: array {name!r} has no valid .npy header (shape {shape})")
                if dtype.hasobject:
                    raise NpzError(f"{where}: array {name!r} holds Python objects (pickled): cannot be read as "
                                  "plain arrays; refused")
                nbytes = math.prod(shape) * dtype.itemsize
                if nbytes > max_bytes or nbytes > info.file_size:
                    raise NpzError(f"{where}: array {name!r} claims shape {shape} {dtype} ({nbytes:,} bytes) but "
                                   f"the file holds {info.file_size:,} bytes for it (limit {max_bytes:,}); it is "
                                   "truncated or corrupt")
                headers[name] = (shape, dtype)
            for name, (shape, dtype) in (expect or {}).items():
                if name not in headers:
                    raise NpzError(f"{where}: no array {name!r} (found {', '.join(headers) or 'none'})")
                want = (tuple(shape), np.dtype(dtype))
                if headers[name] != want:
                    raise NpzError(f"{where}: array {name!r} is {headers[name][0]} {headers[name][1]}, expected "
                                   f"{want[0]} {want[1]}")
            out = {}
            with np.load(path, allow_pickle=False) as z:
                for name in headers:
                    out[name] = z[name]
    except NpzError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, RuntimeError) as err:
        raise NpzError(f"{where}: cannot be read as plain arrays ({type(err).__name__}: {err}); it is truncated, "
                       "corrupt, pickled or not an npz file") from None
    for name, x in out.items():
        check = finite if isinstance(finite, bool) else finite.get(name, True)
        if check and np.issubdtype(x.dtype, np.inexact) and not np.all(np.isfinite(x)):
            bad = int(x.size - np.count_nonzero(np.isfinite(x)))
            raise NpzError(f"{where}: array {name!r} has {bad} non-finite values (NaN or inf) of {x.size}; refused")
    return out
