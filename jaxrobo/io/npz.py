"""``.npz`` files read back as hostile input: every array's header is checked before its data is read.

A checkpoint or a q-table file may be truncated, bit-flipped, pickled, or claim an array of 2^40 rows in its
header; ``np.load`` would raise one of half a dozen exceptions or try to allocate terabytes. :func:`read_npz`
reads each member's ``.npy`` header with :mod:`numpy.lib.format` first (dtype, shape, and the bytes they need
against a cap and against the member's own size in the zip), compares it with an expected template when one
is given, then reads the data (the zip's CRC checks it) and refuses non-finite float arrays. Every failure is
one :class:`NpzError` (a :class:`~jaxrobo.core.config.ConfigError`) naming the file and the array.
"""
from __future__ import annotations

import collections
import contextlib
import errno
import io
import math
import mmap
import os
import struct
import tokenize
import zipfile
import zlib as stdlib_zlib
from concurrent.futures import Future, ThreadPoolExecutor
from typing import IO, Any, Callable, Mapping

import numpy as np
# zlib-ng: deflate streams and CRC-32s that zlib reads, made faster (8 MB blocks of a run's tables on one core of an
# H200 host: run-length deflate 26 -> 15 ms, CRC-32 2.7 -> 1.0 ms; benchmarks/results/h200/zlib_ng.json)
from zlib_ng import zlib_ng as zlib

from jaxrobo.core.config import ConfigError
from jaxrobo.core.environ import usable_cores

#: Largest array (bytes) read from a file by default: a run's tables and carry are far below it.
MAX_ARRAY_BYTES = 16 << 30


class NpzError(ConfigError):
    """An ``.npz`` file that cannot be used: unreadable, or not holding the arrays expected."""


#: Arrays are cut into blocks of this many bytes, each checksummed (and compressed) by a thread of its own
#: (:func:`write_npz_deflated`).
BLOCK_BYTES = 8 << 20
#: Arrays up to this size are deflated at level 1 (:func:`write_npz_deflated`).
SMALL_BYTES = 32 << 20
#: A larger array is deflated only by :data:`DEFLATE_FROM_THREADS` threads or more (with fewer it is stored), block by
#: block: a block of which this share of the bytes or more are zero with run lengths only, another at level 1 where
#: its first :data:`PROBE_BYTES` shrink to :data:`DENSE_RATIO` of their size or less, else as a copy (level 0).
SPARSE_SHARE = 0.9
DEFLATE_FROM_THREADS = 4
PROBE_BYTES = 64 << 10
DENSE_RATIO = 0.8


def write_npz_deflated(path: str | IO[bytes], *, compress: bool = True, threads: int | None = None,
                       **arrays: Any) -> None:
    """``arrays`` to ``path`` (a file name, or a seekable binary file open for writing) as an ``.npz`` that
    ``np.load`` reads like ``np.savez_compressed``'s (``compress=False``: every array stored, the layout of
    ``np.savez``). Each array's ``.npy`` bytes (those ``np.lib.format.write_array`` writes) are written from its
    own memory, in blocks of :data:`BLOCK_BYTES` checksummed and compressed by ``threads`` threads (default: one
    per core here; zlib-ng works without Python's lock) while the file takes the blocks before them, in order.

    Which arrays are deflated: those up to :data:`SMALL_BYTES` at level 1; a larger one only by
    :data:`DEFLATE_FROM_THREADS` threads or more, block by block as :func:`_block` chooses; otherwise it is stored.
    Why: a run's per-env Q-tables are mostly unvisited entries (93 % zero bytes in 1 M cart-pole envs stopped at
    their target), which run lengths shrink twelve-fold, and its episode records (small whole numbers, mostly) to a
    quarter, at 250-550 MB/s a core (zlib-ng on an H200 host); at 1 M envs that is 8 GB and 3 GB, which an H200
    host's disk took 22-34 s to take raw. On 2 cores the deflating would be slower than the disk (0.5 GB of such
    tables: 1.1 s deflated by 4 threads with zlib, 0.4-0.5 s stored), and floats without pattern do not shrink at
    all (hence the probe). Where the file's large arrays are :data:`UNCACHED_ABOVE_BYTES` or more, it goes through
    :class:`UncachedWrites` (where the file system allows it).

    A piece with ``deflated(last)`` (a block of a :class:`~jaxrobo.training.nonzero_copy.NonzeroCopy` deflated on the
    device, :mod:`jaxrobo.speed.device_deflate`) gives its raw deflate bytes (ending on a byte; ending the stream
    where ``last``) and its CRC-32: its array is taken deflated, with any number of threads.

    A value may be a function of no arguments returning a small array (at most :data:`SMALL_BYTES`): it is called
    when its turn comes, after the members before it are written (a checkpoint names the tables' file, written
    meanwhile in another thread, in its last members). A value with ``npy_pieces(BLOCK_BYTES)`` (and ``shape``,
    ``dtype``, ``nbytes``: a :class:`jaxrobo.training.nonzero_copy.NonzeroCopy`) is written from the pieces it
    makes, C-ordered, the same bytes as its dense array's."""
    arrays = {name: value if callable(value) or _pieced(value) else np.asanyarray(value)
              for name, value in arrays.items()}
    if threads is None:
        threads = usable_cores()
    eager = [x for x in arrays.values() if not callable(x)]
    large = sum(x.nbytes for x in eager if x.nbytes > SMALL_BYTES)
    with contextlib.ExitStack() as stack:
        f = stack.enter_context(open(path, "wb")) if isinstance(path, (str, os.PathLike)) else path
        if large >= UNCACHED_ABOVE_BYTES:
            try:
                f = stack.enter_context(UncachedWrites(f))
            except OSError:  # no O_DIRECT here (tmpfs, some network file systems): the page cache, as usual
                pass
        pool = stack.enter_context(ThreadPoolExecutor(threads, thread_name_prefix="jaxrobo-npz")) \
            if threads > 1 and any(x.nbytes > BLOCK_BYTES for x in eager) else None
        writer = _ZipWriter(f)
        for name, value in arrays.items():
            if callable(value):
                value = np.asanyarray(value())
                if value.nbytes > SMALL_BYTES:
                    raise ValueError(f"{name}: an array given as a function must be at most {SMALL_BYTES} bytes")
            header, blocks = _npy_parts(value)
            if value.nbytes <= SMALL_BYTES:
                level = 1 if compress else None
            else:  # blocks deflated already (on the device) are taken deflated however few the threads
                level = -1 if compress and (threads >= DEFLATE_FROM_THREADS
                                            or any(hasattr(b, "deflated") for b in blocks)) else None
            writer.member(f"{name}.npy", header, blocks, level, pool, 2 * threads)
        writer.close()


def _pieced(value: Any) -> bool:
    """Whether ``value`` gives its bytes in pieces (``npy_pieces``) rather than as an array."""
    return not isinstance(value, np.ndarray) and hasattr(value, "npy_pieces")


def _npy_parts(value: Any) -> tuple[bytes, list[Any]]:
    """The ``.npy`` header ``np.lib.format.write_array`` writes for ``value``, and its data in blocks of about
    :data:`BLOCK_BYTES`: views of the array's own memory where it is contiguous (in C or Fortran order), otherwise
    blocks of rows (:class:`_Rows`) copied one at a time by the thread that takes them, so that a strided array (an
    ``[envs, episodes]`` record cut to its written columns) is never copied whole. Pickles are refused."""
    fmt = np.lib.format
    if value.dtype.hasobject:
        raise ValueError("Object arrays cannot be saved when allow_pickle=False")
    head = io.BytesIO()
    if _pieced(value):
        fmt.write_array_header_1_0(head, {"descr": fmt.dtype_to_descr(np.dtype(value.dtype)), "fortran_order": False,
                                          "shape": tuple(value.shape)})
        return head.getvalue(), value.npy_pieces(BLOCK_BYTES)
    fmt.write_array_header_1_0(head, fmt.header_data_from_array_1_0(value))
    fortran = value.flags.f_contiguous and not value.flags.c_contiguous
    if value.flags.c_contiguous or fortran:
        flat = memoryview((value.T if fortran else value).reshape(-1).view(np.uint8) if value.size else b"")
        return head.getvalue(), [flat[i:i + BLOCK_BYTES] for i in range(0, flat.nbytes, BLOCK_BYTES)]
    rows = max(1, BLOCK_BYTES // max(1, value[:1].nbytes))
    return head.getvalue(), [_Rows(value, r, min(r + rows, len(value))) for r in range(0, len(value), rows)]


class _Rows:
    """Rows ``start:stop`` of a strided array, as C-ordered bytes copied when :meth:`view` is called."""

    def __init__(self, value: np.ndarray, start: int, stop: int) -> None:
        self.value, self.start, self.stop = value, start, stop
        self.nbytes = value[start:stop].nbytes

    def view(self) -> memoryview:
        return memoryview(np.ascontiguousarray(self.value[self.start:self.stop]).reshape(-1).view(np.uint8))


def _block(piece: Any, level: int | None, last: bool) -> tuple[bytes | memoryview, int]:
    """One block's bytes as the member holds them, and its CRC-32: the piece's bytes themselves (``level`` None:
    stored), or a piece of one raw deflate stream at ``level``. ``level`` -1: run lengths only where
    :data:`SPARSE_SHARE` of its bytes are zero (unvisited table entries), else level 1 where its first
    :data:`PROBE_BYTES` shrink to :data:`DENSE_RATIO` or less at level 1, else level 0 (a copy). On a core of this
    repository's 2-core machine: 8 MB of cart-pole tables with 93 % zero bytes, 8 ms to 8 % of their size with run
    lengths against 7 ms to 10 % with level 1's matches; 8 MB of normal floats 75 ms at level 1, 6 % larger."""
    if level is not None and hasattr(piece, "deflated"):  # deflated already (jaxrobo.speed.device_deflate)
        return piece.deflated(last)
    data = piece if isinstance(piece, memoryview) else piece.view()  # a _Rows or another maker of its bytes
    crc = zlib.crc32(data)
    if level is None:
        return data, crc
    strategy = zlib.Z_DEFAULT_STRATEGY
    if level < 0:
        zeros = data.nbytes - np.count_nonzero(np.frombuffer(data, np.uint8))
        if zeros >= SPARSE_SHARE * data.nbytes:
            level, strategy = 1, zlib.Z_RLE
        else:
            probe = data[:PROBE_BYTES]
            level = 1 if len(zlib.compress(probe, 1, -15)) <= DENSE_RATIO * probe.nbytes else 0
    # Raw deflate: the pieces concatenate into one stream.
    c = zlib.compressobj(level, zlib.DEFLATED, -15, 8, strategy)
    return c.compress(data) + c.flush(zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH), crc


class _ZipWriter:
    """A zip file (zip64 records throughout, as ``zipfile`` reads them) written member by member to ``f``, each
    member's local header patched with its CRC and sizes once its data is written. Written here rather than
    through ``zipfile`` because zipfile checksums and compresses a member in the caller's thread, in order: at 8 GB
    the checksum alone takes seconds on one core."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f, self._entries = f, []
        self._pos = f.tell()

    def _write(self, data: Any) -> None:
        self._f.write(data)
        self._pos += memoryview(data).nbytes

    def member(self, name: str, header: bytes, blocks: list[memoryview | _Rows], level: int | None,
               pool: ThreadPoolExecutor | None, depth: int) -> None:
        """One member: ``header`` then the ``blocks``' bytes (:func:`_npy_parts`), stored (``level`` None) or
        deflated at ``level`` (-1: :func:`_block` chooses per block); ``depth`` blocks at most are on the way in
        ``pool`` at once."""
        raw = name.encode()
        offset, method = self._pos, 0 if level is None else 8
        self._write(struct.pack("<IHHHHHIIIHH", 0x04034B50, 45, 0, method, 0, _DOS_DATE, 0, _FULL, _FULL,
                                len(raw), 20) + raw + struct.pack("<HHQQ", 1, 16, 0, 0))
        pieces = [memoryview(header)] + blocks
        start, crc, size = self._pos, 0, sum(piece.nbytes for piece in pieces)
        pending: collections.deque = collections.deque()
        for i, piece in enumerate(pieces):
            args = (piece, level, i == len(pieces) - 1)
            pending.append((pool.submit(_block, *args) if pool is not None else _done(_block(*args)), piece.nbytes))
            while pending and (len(pending) > depth or i == len(pieces) - 1):
                future, n = pending.popleft()
                block, block_crc = future.result()
                crc = zlib.crc32_combine(crc, block_crc, n)
                self._write(block)  # small ones are gathered by the file (a buffered file, or UncachedWrites)
        stored = self._pos - start
        self._f.seek(offset + 14)
        self._f.write(struct.pack("<I", crc))
        self._f.seek(offset + 30 + len(raw) + 4)
        self._f.write(struct.pack("<QQ", size, stored))
        self._f.seek(self._pos)
        self._entries.append((raw, method, crc, size, stored, offset))

    def close(self) -> None:
        directory = self._pos
        for raw, method, crc, size, stored, offset in self._entries:
            self._write(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, method, 0, _DOS_DATE, crc, _FULL,
                                    _FULL, len(raw), 28, 0, 0, 0, 0o644 << 16, _FULL)
                        + raw + struct.pack("<HHQQQ", 1, 24, size, stored, offset))
        end, n = self._pos, len(self._entries)
        self._write(struct.pack("<IQHHIIQQQQ", 0x06064B50, 44, 45, 45, 0, 0, n, n, end - directory, directory)
                    + struct.pack("<IIQI", 0x07064B50, 0, end, 1)
                    + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, min(n, 0xFFFF), min(n, 0xFFFF), _FULL, _FULL, 0))
        self._f.flush()


_FULL = 0xFFFFFFFF  # a 32-bit field whose value is in the zip64 record
_DOS_DATE = 33  # 1980-01-01, as np.savez's members (time 00:00)


def _done(value: Any) -> Future:
    """A future already holding ``value`` (a block computed in the caller's thread)."""
    future: Future = Future()
    future.set_result(value)
    return future


#: Stored arrays of at least this many bytes in all are written past the page cache (:class:`UncachedWrites`).
UNCACHED_ABOVE_BYTES = 64 << 20


class UncachedWrites(io.RawIOBase):
    """A binary file open for writing (``f``, at its position), written with ``O_DIRECT`` where the writes are
    large: from a write of :data:`DIRECT_FROM` bytes or more on, the bytes written one after another are gathered
    into page-aligned buffers of :data:`WRITE_CHUNK_BYTES`, each written straight to the disk by a thread of its own
    while the caller fills the next (:data:`BUFFERS` at most on the way); the unaligned ends (the bytes before the
    first whole page, those after the last when :meth:`flush`, :meth:`seek` or :meth:`close` ends the run of
    writes) and every small write on its own (zip headers, their patches) go through ``f``'s descriptor and the
    page cache as usual. A page is written one way only, and a write that goes back (a seek) waits for the direct
    ones before it. Every write is positional; ``f``'s own buffer is not used (close this before using ``f``
    again; its ``fsync`` covers both). An error of the writing thread is raised by the caller's next call and
    every one after it (:meth:`close` raises it only if none did); nothing is left writing after :meth:`close`,
    whatever happened.

    Why: a file of hundreds of MB written through the page cache needs as many fresh pages, which on a virtual
    machine that hands its free memory back to the host cost several times the writing (a 0.5 GB checkpoint:
    seconds, where the same bytes written with ``O_DIRECT`` took a fraction of one, already on the disk). Why the
    thread: one buffer copied then written in turn kept an H200 host's disk (1.9 GB/s written this way alone)
    at 0.7-0.9 GB/s while a 1 M-env run's tables' file (831 MB) was written (``device_deflate_s35.json``,
    ``benchmarks/results/h200/direct_writes_s36.json``). Opening ``O_DIRECT`` raises OSError where the file
    system does not have it."""

    ALIGN = 4096
    #: A write of at least this many bytes starts gathering the writes that follow it (a device-deflated block of
    #: a 1 M-env run's tables is about 0.9 MB).
    DIRECT_FROM = 64 << 10
    #: Buffers filled or being written at once.
    BUFFERS = 3

    def __init__(self, f: IO[bytes]) -> None:
        super().__init__()
        f.flush()
        self._fd, self._pos = f.fileno(), f.tell()
        if not hasattr(os, "O_DIRECT"):
            raise OSError("no O_DIRECT on this system")
        self._direct = os.open(f"/proc/self/fd/{self._fd}", os.O_WRONLY | os.O_DIRECT)
        self._direct_ok = True  # until a direct write is refused (EINVAL): the rest then go through the page cache
        self._size = max(self.ALIGN, WRITE_CHUNK_BYTES // self.ALIGN * self.ALIGN)
        self._buffers: list[mmap.mmap] | None = []  # page-aligned, made as needed (BUFFERS at most), reused
        self._free: list[mmap.mmap] = []
        self._pool: ThreadPoolExecutor | None = None  # one thread: the direct writes, in order
        self._pending: collections.deque = collections.deque()  # (future, buffer) of the writes on the way
        self._error: BaseException | None = None  # the first write that failed; every call after it raises it
        self._error_raised = False
        self._stage: mmap.mmap | None = None  # the buffer being filled: file offset _stage_at (aligned), _filled bytes
        self._stage_at = self._filled = 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        self.flush()
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: os.fstat(self._fd).st_size}[whence]
        self._pos = base + offset
        return self._pos

    def _pwrite(self, fd: int, data: memoryview, offset: int) -> None:
        while data.nbytes:
            n = os.pwrite(fd, data, offset)
            data, offset = data[n:], offset + n

    def _raise_error(self) -> None:
        """The thread's error, if any (every call after it raises it: the file misses bytes)."""
        if self._error is not None:
            self._error_raised = True
            raise self._error

    def _settle_oldest(self) -> mmap.mmap:
        """The oldest write on the way, once done (its error kept for :meth:`_raise_error`); its buffer."""
        future, buffer = self._pending.popleft()
        error = future.exception()
        if error is not None and self._error is None:
            self._error = error
        return buffer

    def _take_buffer(self) -> mmap.mmap:
        """A free buffer: a fresh one while fewer than :data:`BUFFERS` exist, else the oldest write's, once done."""
        if self._free:
            return self._free.pop()
        if len(self._buffers) < self.BUFFERS:
            self._buffers.append(mmap.mmap(-1, self._size))
            return self._buffers[-1]
        buffer = self._settle_oldest()
        self._raise_error()
        return buffer

    def _send(self, buffer: mmap.mmap, offset: int, n: int) -> None:
        """``n`` bytes of ``buffer`` (a whole number of pages) to the thread, for ``offset`` of the file."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="jaxrobo-direct-writes")
        self._pending.append((self._pool.submit(self._write_pages, buffer, offset, n), buffer))

    def _write_pages(self, buffer: mmap.mmap, offset: int, n: int) -> None:
        view = memoryview(buffer)[:n]
        try:
            if self._direct_ok:
                try:
                    self._pwrite(self._direct, view, offset)
                    return
                except OSError as err:  # a device whose blocks are not 4096-aligned: the page cache from here
                    if err.errno != errno.EINVAL:
                        raise
                    self._direct_ok = False
            self._pwrite(self._fd, view, offset)
        finally:
            view.release()

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        n, pos = view.nbytes, self._pos
        self._raise_error()
        if self._stage is None:
            head = (-pos) % self.ALIGN
            if n < self.DIRECT_FROM or n - head < self.ALIGN:  # on its own: through the page cache
                self._pwrite(self._fd, view, pos)
                self._pos = pos + n
                return n
            self._pwrite(self._fd, view[:head], pos)  # up to the first whole page
            self._stage, self._stage_at, self._filled = self._take_buffer(), pos + head, 0
            done = head
        else:
            done = 0
        while done < n:
            k = min(n - done, self._size - self._filled)
            np.copyto(np.frombuffer(self._stage, np.uint8, k, self._filled),  # copied without Python's lock
                      np.frombuffer(view[done:done + k], np.uint8))
            self._filled += k
            done += k
            if self._filled == self._size:
                self._send(self._stage, self._stage_at, self._size)
                self._stage_at += self._size
                self._stage, self._filled = self._take_buffer(), 0
        self._pos = pos + n
        return n

    def flush(self) -> None:
        """The gathered bytes written (the whole pages direct, the rest through the page cache) and every direct
        write done."""
        if self.closed or self._buffers is None:
            return
        if self._stage is not None:
            stage, at, filled = self._stage, self._stage_at, self._filled
            self._stage = None
            pages = filled // self.ALIGN * self.ALIGN
            if pages:
                self._send(stage, at, pages)
            with memoryview(stage) as rest:  # bytes of the buffer the thread does not touch
                self._pwrite(self._fd, rest[pages:filled], at + pages)
            if not pages:
                self._free.append(stage)
        while self._pending:  # every write done, whatever the first one's error
            self._free.append(self._settle_oldest())
        self._raise_error()

    def close(self) -> None:
        if self.closed:
            return
        try:
            raised = self._error_raised
            try:
                self.flush()
            except BaseException:
                if not raised:  # said once: a close while the caller's error unwinds does not raise it again
                    raise
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
            os.close(self._direct)
            for buffer in self._buffers:
                with contextlib.suppress(BufferError):  # a view still held (a traceback's frame): freed with it
                    buffer.close()
            self._buffers = None  # flush() (IOBase.close calls it) has nothing left to do
            super().close()


#: Bytes of each of :class:`UncachedWrites`' buffers: written to the disk at once.
WRITE_CHUNK_BYTES = 16 << 20


def _header(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype]:
    from numpy.lib import format as npy

    with zf.open(info) as f:
        version = npy.read_magic(f)
        reader = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}.get(tuple(version))
        if reader is None:
            raise ValueError(f"unknown .npy format version {version}")
        shape, _fortran, dtype = reader(f)
    return tuple(int(n) for n in shape), np.dtype(dtype)


def member_headers(path: str) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """``{name: (shape, dtype)}`` of each array of the ``.npz`` at ``path``, in the file's order, from the members'
    ``.npy`` headers alone (no data read); :class:`NpzError` where a header cannot be read."""
    try:
        with zipfile.ZipFile(path) as zf:
            return {info.filename[:-4] if info.filename.endswith(".npy") else info.filename: _header(zf, info)
                    for info in zf.infolist()}
    except (OSError, ValueError, SyntaxError, TypeError, OverflowError, EOFError, zipfile.BadZipFile,
            tokenize.TokenError, stdlib_zlib.error, zlib.error) as err:
        raise NpzError(f"{path}: cannot read its arrays' headers ({type(err).__name__}: {err})") from None


def read_npz(path: str, what: str = "the file", *, expect: Mapping[str, tuple[tuple[int, ...], Any]] | None = None,
             finite: bool | Mapping[str, bool] = True, max_bytes: int = MAX_ARRAY_BYTES,
             wanted: Callable[[str], bool] | None = None) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, checked before and after reading (see the module).

    ``expect``: ``{name: (shape, dtype)}`` the arrays must have (a name missing from the file is an error; names
    not in ``expect`` are read too, under ``max_bytes``). ``wanted``: where given, only the members it accepts are
    checked and read (a member nobody reads could otherwise inflate to ``max_bytes`` from a few kilobytes of file).
    ``finite``: refuse float arrays holding NaN or inf (all, or per name). Raises :class:`NpzError` naming
    ``what``, the file and the array."""
    where = f"{path}: {what}"
    from jaxrobo.core.config import check_regular

    check_regular(path, where)  # a FIFO would hang the read, a device never end it
    try:
        with zipfile.ZipFile(path) as zf:
            infos = {i.filename[:-4] if i.filename.endswith(".npy") else i.filename: i for i in zf.infolist()}
            if wanted is not None:
                infos = {name: info for name, info in infos.items() if wanted(name)}
            headers = {}
            for name, info in infos.items():
                try:
                    shape, dtype = _header(zf, info)
                # tokenize.TokenError: numpy tokenizes a header it cannot parse (an unclosed bracket)
                except (ValueError, SyntaxError, TypeError, OverflowError, tokenize.TokenError) as err:
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
    # zipfile inflates with the standard library's zlib, whose error is not zlib-ng's (a damaged deflate stream).
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, stdlib_zlib.error, zlib.error, KeyError,
            RuntimeError) as err:
        raise NpzError(f"{where}: cannot be read as plain arrays ({type(err).__name__}: {err}); it is truncated, "
                       "corrupt, pickled or not an npz file") from None
    for name, x in out.items():
        check = finite if isinstance(finite, bool) else finite.get(name, True)
        if check and np.issubdtype(x.dtype, np.inexact) and not np.all(np.isfinite(x)):
            bad = int(x.size - np.count_nonzero(np.isfinite(x)))
            raise NpzError(f"{where}: array {name!r} has {bad} non-finite values (NaN or inf) of {x.size}; refused")
    return out
