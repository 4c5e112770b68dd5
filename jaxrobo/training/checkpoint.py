"""Checkpoints: a training carry saved whole to one ``.npz`` and loaded back only into the run that wrote it.

``jaxrobo train`` saves its carry (:func:`save_checkpoint`) now and then and when interrupted;
``jaxrobo train --resume`` reads it back (:func:`load_checkpoint`), refusing with :class:`CheckpointError` a
checkpoint whose fingerprint (:func:`carry_fingerprint`: the resolved run config, the library versions, the
carry's structure and the sources' hash) differs from the run's own, saying what differs
(:func:`fingerprint_mismatch`). ``jaxrobo sweep`` keeps the metrics of its finished groups in the same kind of
file (:mod:`jaxrobo.training.sweep`): both write through :func:`write_npz` (atomic, no pickled objects) and read through
:func:`read_npz`.

A run's checkpoint may keep the learner's tables and its episode records in files of their own beside it, laid out
as the results' ``qtables.npz`` and ``records.npz`` (:func:`save_checkpoint`'s ``tables`` and ``epsilon``): the
finished run links those files as its results, so the tables and records are written once.

Public surface: :data:`CHECKPOINT_FORMAT`, :data:`TABLES_LEAF`, :data:`EPISODE_LEAF`, :class:`CheckpointError`,
:class:`Saved`, :class:`SaveInThread`,
:func:`carry_template`, :func:`carry_fingerprint`, :func:`fingerprint_mismatch`, :func:`save_checkpoint`,
:func:`read_fingerprint`, :func:`load_checkpoint`, :func:`write_npz`, :func:`read_npz`.
"""
from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import secrets
import threading
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.io import rundir
from jaxrobo.speed import locked_copy
from jaxrobo.training import nonzero_copy
from jaxrobo.core import rng
from jaxrobo.core.config import ConfigError, flat_keys, parse_json
from jaxrobo.core.environ import in_threads, usable_cores
from jaxrobo.core.memo import IdentityMemo

if TYPE_CHECKING:
    from jaxrobo.tabular.learner import AgentParams
    from jaxrobo.training.trainer import Runner, Trainer

#: Bumped when the checkpoint layout changes (2: the episode records saved up to their last written column).
CHECKPOINT_FORMAT = 2

#: Leaves of the carry holding per-episode records (``[n_envs, nepisodes]``, zeros until an episode is written):
#: a checkpoint keeps their columns up to the last one written (``records_<i>``, :func:`cut_records`), the loader
#: pads the zeros back. At 65,536 envs and 1,000 episodes they are 590 MB, of which a run that learns in tens of
#: episodes writes a few percent.
RECORD_LEAVES = (".returns", ".lengths", ".terminated")


#: The latest carry's cut records only: a carry is cut at a run's end, by its checkpoint and for its result.
_CUT = IdentityMemo(latest_only=True)


def cut_records(tree: Any, *, from_bytes: int = 64 << 20) -> Any:
    """``tree`` (a carry) with its episode records (:data:`RECORD_LEAVES`, ``[n_envs, nepisodes]`` on the device)
    cut, on the device, to the columns up to the last one any of them wrote, so that only those cross to the
    host: at 1 M envs x 1,000 episodes the records are 9.4 GB, of which a run stopped at its learning target wrote
    a third; an H200 host copied them whole in 6.0 s, and with 8 GB of tables in 11.0 s whole, 6.0 s cut.
    Cutting the same arrays again (the closing checkpoint's thread, then the result) gives the same arrays while
    the first ones live, so their bytes cross once. Records under ``from_bytes`` in all (a copy of them is quick;
    cutting them would compile small programs of its own) and a carry split over several processes are returned
    whole."""
    with_paths, treedef = jax.tree_util.tree_flatten_with_path(tree)
    leaves = [x for _, x in with_paths]
    index = [i for i, (keypath, x) in enumerate(with_paths)
             if jax.tree_util.keystr(keypath) in RECORD_LEAVES and isinstance(x, jax.Array) and x.ndim == 2]
    records = [leaves[i] for i in index]
    if not index or jax.process_count() > 1 or sum(x.nbytes for x in records) < from_bytes:
        return tree

    def cut() -> list[Any]:
        written = np.asarray(functools.reduce(jnp.logical_or, [jnp.any(x != 0, axis=0) for x in records]))
        columns = np.flatnonzero(written)
        k = int(columns[-1]) + 1 if columns.size else 0
        return [x if k >= x.shape[1] else x[:, :k] for x in records]

    for i, x in zip(index, _CUT.get_or_make(records, cut)):
        leaves[i] = x
    return jax.tree.unflatten(treedef, leaves)


def pad_columns(x: np.ndarray, width: int, *, threaded_from: int = 64 << 20) -> np.ndarray:
    """``x`` (``[rows, k]``, cut by :func:`cut_records`) with zero columns after it up to ``width``, in Fortran
    order: the zero columns are memory nothing writes (``np.zeros`` takes it zeroed from the system and no page
    of it is touched), where a C-ordered copy touches every row's page (first touches of fresh memory were the
    cost: at 65,536 envs x 23 of 1,000 columns on 2 CPU cores 1.1 s, now 0.015 s; at 1,048,576 envs x 330
    columns 8.6-12.3 s, now 1.7-2.1 s). The values are the same arrays'; the consumers whose reductions sum in
    the order of the memory they read copy their blocks in C order (:func:`jaxrobo.io.results.episode_stats`), and
    ``records.npz`` stores them as they lie (``np.load`` reads either order). An ``x`` of ``threaded_from`` bytes
    or more is copied in blocks of rows by a thread per core."""
    if x.ndim != 2 or x.shape[1] >= width:
        return x
    out = np.zeros((x.shape[0], width), x.dtype, order="F")
    k = x.shape[1]

    def fill(start: int, stop: int) -> None:
        out[start:stop, :k] = x[start:stop]

    threads = 1 if x.nbytes < threaded_from else usable_cores()
    step = PAD_BLOCK_ROWS if threads > 1 else max(x.shape[0], 1)
    starts = list(range(0, x.shape[0], step))
    in_threads(fill, starts, [min(a + step, x.shape[0]) for a in starts], threads=threads, name="jaxrobo-pad")
    return out


#: Rows per block of :func:`pad_columns` (a block's columns are as many runs of contiguous memory in the output;
#: 4,096-16,384 rows were the fastest at 65,536 and 1,048,576 envs on 2 CPU cores).
PAD_BLOCK_ROWS = 8192


class CheckpointError(ConfigError):
    """A checkpoint that cannot be loaded: unreadable, or from another config or code version (a
    :class:`~jaxrobo.core.config.ConfigError`: the command refuses it at its boundary, exit status 2)."""


def write_npz(path: str, **arrays: Any) -> None:
    """``arrays`` (plain arrays, no pickled objects) to ``path`` as an uncompressed ``.npz``, atomically: a reader
    or a crash sees the previous file or this one, never a torn one (:func:`jaxrobo.io.rundir.atomic_savez`).

    Why npz rather than orbax-checkpoint: what is saved is one single-host pytree of a few arrays (or a few
    metrics), written now and then as a whole; npz does that with numpy alone, while orbax is a heavy dependency
    (tensorstore, async managers, a directory layout per step) that brings nothing a single host needs."""
    rundir.atomic_savez(path, **arrays)


def read_npz(path: str, what: str = "the checkpoint", **checks: Any) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, read as a hostile file (:func:`jaxrobo.io.npz.read_npz`: headers
    checked for dtype, shape and size before any data is read; ``checks`` are its ``expect``, ``finite``,
    ``max_bytes``); :class:`CheckpointError` naming ``what`` when it cannot be used."""
    from jaxrobo.io.npz import NpzError, read_npz as read_checked

    checks.setdefault("finite", False)
    try:
        return read_checked(path, what, **checks)
    except NpzError as err:
        raise CheckpointError(str(err)) from None


#: Leaves of the carry that must be finite in a checkpoint (the learner's tables and exploration rate): a table of
#: NaN under a copied fingerprint would otherwise resume into a "complete" run of NaN. The env state may hold a
#: non-finite physics state that the next step resets, so it is not checked.
FINITE_LEAVES = (".agent", ".q_rows", ".epsilon")


def _is_key(x: Any) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def carry_template(trainer: Trainer, agent_params: AgentParams, env_params: Any = None) -> Runner:
    """The carry's structure, shapes and dtypes (``ShapeDtypeStruct`` leaves), traced without compiling.

    Traced as :func:`jaxrobo.training.driver.compiled_init` traces it (:attr:`Trainer.jitted_init
    <jaxrobo.training.trainer.Trainer.jitted_init>`, under the trainer's plan), so a run given this trainer
    (:func:`jaxrobo.training.train.train`'s ``trainer``) compiles its first carry from this trace instead of
    tracing the env's reset again."""
    env_params = trainer.env.default_params if env_params is None else env_params
    args = (rng.seed_key(trainer.config.seed), agent_params, env_params)
    if trainer.plan.reuse_traces:  # the init an earlier process kept says its carry's shapes without a trace
        from jaxrobo.speed import reuse

        kept = reuse.kept_shapes(trainer.plan, "init", args, trainer)
        if kept is not None:
            return kept
    with trainer.plan.tracing():
        return jax.eval_shape(trainer.jitted_init, *args)


def carry_fingerprint(template: Runner, run_config: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint must match to be loaded: the resolved run config, the jaxrobo and JAX versions, the carry's
    tree structure and leaf shapes/dtypes, and the hash of the sources (:func:`jaxrobo.core.version.source_hash`)."""
    from jaxrobo.core.version import __version__, source_hash

    leaves, treedef = jax.tree.flatten(template)
    return json.loads(json.dumps({
        "format": CHECKPOINT_FORMAT, "config": run_config, "jaxrobo": __version__, "jax": jax.__version__,
        "treedef": str(treedef), "leaves": [[list(x.shape), str(x.dtype)] for x in leaves],
        "sources": source_hash()}))


def tables_copy_first(tables: jax.Array) -> bool:
    """Whether a checkpoint's tables start their host copy before the rest of the carry: on CPUs (see
    :func:`save_checkpoint`)."""
    return {d.platform for d in tables.devices()} == {"cpu"}


class Saved(NamedTuple):
    """The files beside a checkpoint that :func:`save_checkpoint` wrote (None: not written): ``tables``, laid out
    as the results' ``qtables.npz``, and ``records``, laid out as their ``records.npz``."""

    tables: str | None = None
    records: str | None = None


def save_checkpoint(path: str, runner: Runner, chunks_done: int, fingerprint: dict[str, Any], *,
                    tables: dict[str, Any] | None = None, epsilon: np.ndarray | None = None) -> Saved:
    """Write the whole training carry to ``path`` (``.npz``), atomically.

    Layout (``np.savez``, no pickled objects, so ``np.load(allow_pickle=False)`` reads it): ``leaf_<i>`` the
    i-th leaf of ``jax.tree.flatten(runner)`` as a plain array (a PRNG key array as its ``jax.random.key_data``),
    except the episode records (:data:`RECORD_LEAVES`), saved as ``records_<i>`` up to the last column that is
    not all zeros in any of them (:func:`cut_records`); ``key_impls`` a JSON list with each leaf's PRNG
    implementation name or null, ``chunks_done`` the number of chunks the carry has run, and ``fingerprint`` the
    JSON of :func:`carry_fingerprint`.

    ``tables`` (the discretiser's arrays of ``qtables.npz``, :func:`jaxrobo.io.results.discretiser_arrays`): the
    learner's tables (:data:`TABLES_LEAF`, hundreds of MB at tens of thousands of envs) go to a file of their own
    beside ``path``, laid out as the results' ``qtables.npz`` (``q`` with a leading axis of envs, one for a shared
    table, and these arrays), so that a finished run links that file as its results instead of writing the tables
    twice. The file has a fresh name (:data:`jaxrobo.io.rundir.CHECKPOINT_TABLES`) and lands before the
    checkpoint, which names it (``tables_file``) with the CRC-32 of its ``q`` (``tables_crc``); the previous
    checkpoint's file is removed only after: whenever the process stops, the checkpoint on disk names a whole
    file.

    ``epsilon`` (the run's exploration per episode, ``records.npz``'s): the episode records go to a file of their
    own in the same way (:data:`jaxrobo.io.rundir.CHECKPOINT_RECORDS`, named in ``records_file`` with the CRC-32s of
    the record leaves' members in ``records_crc``), laid out as the results' ``records.npz``
    (:func:`jaxrobo.io.results.records_members`, the count of each env's recorded episodes from the carry's
    :data:`EPISODE_LEAF`), so that a finished run links it too: at 1 M envs the records were otherwise written
    twice (3 GB stored in the checkpoint, then deflated in the results), 4.2 s and 2.2 s of a run's writing on
    an H200 host. Where the records' cut and that count disagree (an episode that wrote only zeros), the records
    stay in the checkpoint. Both files: one process only (several gather the carry whole).

    Returns the files written (:class:`Saved`)."""
    uncut = jax.tree_util.tree_flatten_with_path(runner)[0]
    whole = [x.shape for _, x in uncut]
    table = next((i for i, (keypath, _) in enumerate(uncut) if jax.tree_util.keystr(keypath) == TABLES_LEAF),
                 None) if tables is not None else None
    directory = os.path.dirname(os.path.abspath(path))
    # One process: the tables' file is written from their host copy in a thread while the rest is cut, copied and
    # written (the checkpoint's file waits for the tables' name and CRC as its last members). On a CPU the tables'
    # copy starts first (the cut reads every record: 0.25 s of 0.7 at 65,536 envs on 2 cores); on an accelerator
    # the host copies queue on one link, so the records (the results wait for them) cross first and the tables
    # after them (an H200 at 65,536 envs: the cut waited 0.56 s behind the tables' 0.5 GB). Several processes
    # gather every leaf together (collectives in one order).
    one = table is not None and jax.process_count() == 1
    tables_first = one and tables_copy_first(uncut[table][1])
    pool = ThreadPoolExecutor(1, thread_name_prefix="jaxrobo-tables") if one else None
    try:
        def start_tables():
            return pool.submit(lambda: _write_tables(directory, nonzero_copy.file_copy(uncut[table][1]), tables))
        pending = start_tables() if tables_first else None
        with_paths = jax.tree_util.tree_flatten_with_path(cut_records(runner))[0]
        leaves = [x for _, x in with_paths]
        records = {i for i, (keypath, x) in enumerate(with_paths)
                   if jax.tree_util.keystr(keypath) in RECORD_LEAVES and x.ndim == 2}
        impls = [str(jax.random.key_impl(x)) if _is_key(x) else None for x in leaves]
        data = [jax.random.key_data(x) if _is_key(x) else x for x in leaves]
        if jax.process_count() > 1:  # a carry split over several processes' devices: every process gathers it
            from jaxrobo.speed import sharding

            host = sharding.gather(data)
        else:
            rest = [None if i == table else x for i, x in enumerate(data)]
            if one and not tables_first:
                for x in jax.tree.leaves(rest):
                    if locked_copy.why_not(x) is not None and isinstance(x, jax.Array):
                        x.copy_to_host_async()  # queued before the tables' (the large ones: by locked_copy, below)
                pending = start_tables()
            host = locked_copy.get(rest)
        arrays, cut = {}, {}
        for i, x in enumerate(host):
            x = np.asarray(x)
            if i in records:
                if x.shape == whole[i]:  # not cut on the device (small, or gathered from several processes): cut here
                    written = np.flatnonzero(x.any(axis=0))
                    x = x[:, :int(written[-1]) + 1 if written.size else 0]
                cut[i] = x
            elif i != table:
                arrays[f"leaf_{i}"] = x
        members = _records_members(with_paths, host, cut, whole, epsilon) if jax.process_count() == 1 else None
        records_path = None
        if members is None:
            arrays.update({f"records_{i}": x for i, x in cut.items()})
        else:  # written here while the tables are written in their thread; named below, once whole on disk
            records_path, crcs = _write_beside(directory, "records", members, [_member(with_paths[i][0]) for i in cut])
            arrays.update(records_file=np.array(os.path.basename(records_path)), records_crc=np.array(crcs, np.int64))
        arrays.update(key_impls=np.array(json.dumps(impls)), chunks_done=np.int64(chunks_done),
                      fingerprint=np.array(json.dumps(fingerprint, sort_keys=True)))
        if table is not None:  # the checkpoint's last members: its other members are written while the tables are
            @functools.cache
            def tables_written() -> tuple[str, int]:
                return pending.result() if pending is not None else \
                    _write_tables(directory, np.asarray(host[table]), tables)

            arrays.update(tables_file=lambda: np.array(os.path.basename(tables_written()[0])),
                          tables_crc=lambda: np.int64(tables_written()[1]))
        write_npz(path, **arrays)
        saved = Saved(tables_written()[0] if table is not None else None, records_path)
    finally:
        if pool is not None:
            pool.shutdown(wait=True)  # a failure above still leaves no thread writing
    if saved.tables or saved.records:  # the checkpoint on disk names its files now: the older ones are not needed
        for name in os.listdir(directory):
            if _BESIDE_NAME.fullmatch(name) and os.path.join(directory, name) not in saved:
                with contextlib.suppress(OSError):
                    os.unlink(os.path.join(directory, name))
    return saved


class SaveInThread:
    """A run's checkpoints through ``save(carry, chunks_done)``: those on the way as they come (the next chunk
    reuses the carry's buffers), the one after the last chunk (:meth:`last`, called by
    :func:`jaxrobo.training.driver.run_chunks`) in a thread, while the run evaluates and computes its results;
    :meth:`wait` before anything that needs it on disk (publishing the results, marking the run interrupted,
    saying that a failed run can be resumed). The thread is not a daemon: an exit waits for the checkpoint, as it
    waited for a save in the caller's thread. ``seconds`` is how long the last save took to write, ``waited``
    how long :meth:`wait` held the caller.

    :meth:`hold` (the driver's, around its training and greedy evaluation) has the closing save's thread wait for
    :meth:`release` before it reads the carry, at most :data:`HOLD_SECONDS`: the evaluation's few reads from the
    device wait behind that copy of the whole carry (1,048,576 envs on an H200: the evaluation took 5.7-7.0 s in
    runs whose copy was under way, 0.085 s in one whose copy started later: writing_parallel.json; the hold's own
    effect: 0.06 s, run_end.json). The save is handed over before the evaluation either way, and a failed
    or stopped evaluation releases it."""

    #: The longest the closing save waits for :meth:`release` once held (a hung evaluation never holds it longer).
    HOLD_SECONDS = 10.0

    def __init__(self, save: Callable[[Any, int], None]) -> None:
        self._save = save
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._go = threading.Event()
        self._go.set()
        self.seconds = self.waited = 0.0

    def hold(self) -> None:
        """The next closing save (:meth:`last`) starts at :meth:`release`, or :data:`HOLD_SECONDS` after it is
        handed over."""
        self._go.clear()

    def release(self) -> None:
        self._go.set()

    def __call__(self, carry: Any, chunks_done: int) -> None:
        self.wait()
        self._save(carry, chunks_done)

    def last(self, carry: Any, chunks_done: int) -> None:
        self.wait()
        if jax.process_count() > 1:
            # Under jax.distributed the save gathers the carry, a collective: in a thread it met the evaluation's
            # collectives in another order in each process (Gloo's 'collective mismatch', every process aborted
            # at the end of a run; a hang on GPUs). Saved here, before the evaluation, as every save on the way.
            t = time.perf_counter()
            self._save(carry, chunks_done)
            self.seconds = time.perf_counter() - t
            return

        def run() -> None:
            self._go.wait(self.HOLD_SECONDS)
            t = time.perf_counter()
            try:
                self._save(carry, chunks_done)
            except BaseException as err:  # handed to the caller's thread by wait()
                self._error = err
            self.seconds = time.perf_counter() - t

        self._thread = threading.Thread(target=run, name="jaxrobo-checkpoint")
        self._thread.start()

    def wait(self) -> None:
        """Return once no save is being written; raise the error the last one ended with, if any (once)."""
        if self._thread is not None:
            t = time.perf_counter()
            self._thread.join()
            self.waited += time.perf_counter() - t
            self._thread = None
        error, self._error = self._error, None
        if error is not None:
            raise error


#: The carry's leaf of the learner's tables (``[n_envs, n_tables, n_states, n_actions]``; a shared table's
#: ``[n_tables, n_states, n_actions]``): what :func:`save_checkpoint` may keep in a file of its own.
TABLES_LEAF = ".agent.q"
#: The carry's leaf counting each env's finished episodes (``[n_envs]``): those up to ``nepisodes`` are recorded.
EPISODE_LEAF = ".episode"
#: The names those files take (:data:`jaxrobo.io.rundir.CHECKPOINT_TABLES`, ``CHECKPOINT_RECORDS``); a checkpoint
#: naming another is refused.
_TABLES_NAME, _RECORDS_NAME, _BESIDE_NAME = (re.compile(rf"checkpoint\.({kinds})\.[0-9a-f]{{8}}\.npz")
                                             for kinds in ("tables", "records", "tables|records"))


def _member(keypath: Any) -> str:
    """The member of a checkpoint's records file holding the record leaf at ``keypath`` (``.returns``:
    ``returns``)."""
    return jax.tree_util.keystr(keypath).lstrip(".")


def _write_beside(directory: str, kind: str, arrays: dict[str, Any], crc_of: list[str]) -> tuple[str, list[int]]:
    """``arrays`` to a fresh ``checkpoint.<kind>.<id>.npz`` in ``directory``, atomically and flushed to disk (as the
    results' files are written: :func:`jaxrobo.io.npz.write_npz_deflated`); returns its path and the CRC-32s of its
    members ``crc_of``."""
    from jaxrobo.io.npz import write_npz_deflated

    while True:
        path = os.path.join(directory, f"checkpoint.{kind}.{secrets.token_hex(4)}.npz")
        if not os.path.lexists(path):
            break
    rundir.atomic_write(path, lambda f: write_npz_deflated(f, **arrays))
    with zipfile.ZipFile(path) as zf:
        return path, [zf.getinfo(f"{name}.npy").CRC for name in crc_of]


def _write_tables(directory: str, q: Any, extra: dict[str, Any]) -> tuple[str, int]:
    """``q`` (an array or its :class:`~jaxrobo.training.nonzero_copy.NonzeroCopy`; a shared table given a leading
    axis of one) and ``extra`` to a fresh ``checkpoint.tables.<id>.npz`` in ``directory`` (:func:`_write_beside`);
    returns its path and the CRC-32 of its ``q``."""
    path, (crc,) = _write_beside(directory, "tables", {"q": q if q.ndim == 4 else q[None], **extra}, ["q"])
    return path, crc


def _records_members(with_paths: list, host: list, cut: dict[int, np.ndarray], whole: list[tuple[int, ...]],
                     epsilon: np.ndarray | None) -> dict[str, np.ndarray] | None:
    """The carry's episode records (``cut``: record leaf index -> its columns up to the last written) laid out as
    the results' ``records.npz`` (:func:`jaxrobo.io.results.records_members`), the count of recorded episodes
    from :data:`EPISODE_LEAF` of ``host`` (the carry's leaves on the host); None without ``epsilon``, without those
    three records and that count, or where the cut and the count disagree (the records then stay in the
    checkpoint: each of their written columns is kept)."""
    from jaxrobo.io.results import records_members

    names = {_member(with_paths[i][0]): i for i in cut}
    episode = next((i for i, (keypath, _) in enumerate(with_paths) if jax.tree_util.keystr(keypath) == EPISODE_LEAF),
                   None)
    if epsilon is None or episode is None or set(names) != {"returns", "lengths", "terminated"}:
        return None
    width = whole[names["returns"]][1]
    if {whole[i] for i in names.values()} != {whole[names["returns"]]} or np.shape(epsilon) != (width,):
        return None
    done = np.minimum(np.asarray(host[episode]), width)
    try:
        members = records_members(*(cut[names[n]] for n in ("returns", "lengths", "terminated")), epsilon,
                                  None if bool(np.all(done >= width)) else done, width=width)
    except ValueError:
        return None
    if any(members[n].shape != cut[names[n]].shape for n in names):
        return None  # written columns past the recorded count: kept in the checkpoint, whole
    return members


def read_fingerprint(path: str) -> tuple[dict[str, Any], int]:
    """A checkpoint's fingerprint and chunk count (the whole file is checked as :func:`read_npz` does)."""
    data = read_npz(path, "the checkpoint")
    try:
        return parse_json(str(data["fingerprint"])), int(data["chunks_done"])
    except (KeyError, ValueError, TypeError) as err:
        raise CheckpointError(f"{path}: not a jaxrobo checkpoint ({err})") from None


def fingerprint_mismatch(saved: dict[str, Any], expected: dict[str, Any]) -> str | None:
    """Why a checkpoint with fingerprint ``saved`` cannot go on as ``expected`` (None if it can)."""
    what = {"format": "checkpoint format", "config": "configuration", "jaxrobo": "jaxrobo version",
            "jax": "JAX version", "treedef": "training carry structure", "leaves": "training carry shapes/dtypes",
            "sources": "jaxrobo/envs/agents source code"}
    for field, name in what.items():
        if saved.get(field) != expected.get(field):
            if field == "config":
                a, b = flat_keys(saved.get("config") or {}), flat_keys(expected.get("config") or {})
                keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
                diff = ", ".join(f"{k}: {a.get(k)!r} in the checkpoint vs {b.get(k)!r} now" for k in keys[:5])
                return f"the configuration differs ({diff})"
            if field in ("jaxrobo", "jax"):
                return f"it was written by {name} {saved.get(field)} (this is {expected.get(field)})"
            return f"the {name} differs from the one that wrote it"
    return None



def _read_tables(path: str, data: dict[str, np.ndarray], i: int, spec: Any) -> np.ndarray:
    """The tables leaf (``leaf_<i>``, of ``spec``'s shape and dtype) of the checkpoint at ``path`` whose arrays are
    ``data``: its own ``leaf_<i>``, or the file it names (``tables_file``, beside it) whose ``q`` has the CRC-32 it
    recorded (``tables_crc``), read as hostile; :class:`CheckpointError` saying why when neither fits."""
    shape, dtype = tuple(spec.shape), np.dtype(spec.dtype)
    x = data.get(f"leaf_{i}")
    if x is None and "tables_file" in data:
        where, name = _beside(path, data, "tables", _TABLES_NAME)
        full = (1,) + shape if len(shape) == 3 else shape  # a shared table is kept with a leading axis of one
        x = read_npz(where, "the checkpoint's tables", expect={"q": (full, dtype)}, finite={"q": True})["q"]
        try:
            with zipfile.ZipFile(where) as zf:
                crc = zf.getinfo("q.npy").CRC
            recorded = int(data["tables_crc"])
        except (OSError, KeyError, ValueError, TypeError, zipfile.BadZipFile) as err:
            raise CheckpointError(f"{path}: its tables ({name}) cannot be matched to it ({err})") from None
        if crc != recorded:
            raise CheckpointError(f"{path}: {name} holds other tables than the checkpoint recorded (CRC-32 "
                                  f"{crc:#010x}, recorded {recorded & 0xFFFFFFFF:#010x})")
        x = x.reshape(shape)
    if x is None:
        raise CheckpointError(f"{path}: leaf {i} (the tables) is missing")
    if x.shape != shape or x.dtype != dtype:
        raise CheckpointError(f"{path}: leaf {i} (the tables) is {x.shape} {x.dtype}, expected {shape} {dtype}")
    return x


def _beside(path: str, data: dict[str, np.ndarray], kind: str, pattern: re.Pattern) -> tuple[str, str]:
    """The file beside the checkpoint at ``path`` that ``data``'s ``<kind>_file`` names: ``(its path, its name)``;
    :class:`CheckpointError` where that is not such a file's name or the file is missing."""
    field = data[f"{kind}_file"]
    name = str(field) if field.ndim == 0 else ""
    if not pattern.fullmatch(name):
        raise CheckpointError(f"{path}: its {kind}_file {name[:80]!r} is not a checkpoint's {kind} file name")
    where = os.path.join(os.path.dirname(os.path.abspath(path)), name)
    if not os.path.exists(where):
        raise CheckpointError(f"{path}: its {kind} ({name}) are missing beside it")
    return where, name


def _read_records(path: str, data: dict[str, np.ndarray], records: dict[int, tuple[str, Any]]) -> None:
    """Into ``data``, each record leaf's ``records_<i>`` (``records``: leaf index -> its member's name and spec)
    from the file the checkpoint at ``path`` names (``records_file``, beside it), whose members have the CRC-32s
    it recorded (``records_crc``), read as hostile; :class:`CheckpointError` saying why when it does not fit. A
    checkpoint holding its records itself (``records_<i>``) is left as it is."""
    if "records_file" not in data:
        return
    where, name = _beside(path, data, "records", _RECORDS_NAME)
    arrays = read_npz(where, "the checkpoint's records")
    order = sorted(records)
    try:
        with zipfile.ZipFile(where) as zf:
            crcs = [zf.getinfo(f"{records[i][0]}.npy").CRC for i in order]
        recorded = [int(c) & 0xFFFFFFFF for c in np.asarray(data["records_crc"]).reshape(-1)]
    except (OSError, KeyError, ValueError, TypeError, zipfile.BadZipFile) as err:
        raise CheckpointError(f"{path}: its records ({name}) cannot be matched to it ({err})") from None
    if crcs != recorded:
        raise CheckpointError(f"{path}: {name} holds other records than the checkpoint recorded (CRC-32s "
                              f"{', '.join(f'{c:#010x}' for c in crcs)}, recorded "
                              f"{', '.join(f'{c:#010x}' for c in recorded)})")
    for i in order:
        data[f"records_{i}"] = arrays[records[i][0]]


def load_checkpoint(path: str, template: Runner, fingerprint: dict[str, Any],
                    max_chunks: int | None = None) -> tuple[Runner, int]:
    """The carry saved at ``path`` and its chunk count, on the default device, checked against ``fingerprint``
    (:func:`carry_fingerprint` of this run) and ``template``'s structure: refused with :class:`CheckpointError`
    saying why, rather than loaded, when they differ, when the chunk count is not in ``0..max_chunks`` (the run's
    chunks, where given) or an env's episode count (:data:`EPISODE_LEAF`) is negative: a counter the run would
    trust to the end (a count past the budget marks a run complete that trained nothing)."""
    with_paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    specs = [spec for _, spec in with_paths]
    expect, finite, records, table = {}, {}, {}, None
    for i, (keypath, spec) in enumerate(with_paths):
        shape, dtype = spec.shape, spec.dtype
        if _is_key(spec):  # saved as its key data
            data_spec = jax.eval_shape(jax.random.key_data, spec)
            shape, dtype = data_spec.shape, data_spec.dtype
        if jax.tree_util.keystr(keypath) in RECORD_LEAVES and len(shape) == 2:
            records[i] = (_member(keypath), spec)  # records_<i>, or in a file of its own: checked and padded below
            finite[f"records_{i}"] = False  # as the full leaf was: an episode of NaN physics may hold a NaN return
            continue
        finite[f"leaf_{i}"] = jax.tree_util.keystr(keypath).startswith(FINITE_LEAVES)
        if jax.tree_util.keystr(keypath) == TABLES_LEAF:
            table = i  # leaf_<i>, or a file of its own (tables_file): checked below
            continue
        expect[f"leaf_{i}"] = (tuple(shape), dtype)
    data = read_npz(path, "the checkpoint", expect=expect, finite=finite)
    if table is not None:
        data[f"leaf_{table}"] = _read_tables(path, data, table, specs[table])
    _read_records(path, data, records)
    for i, (_, spec) in records.items():
        x = data.pop(f"records_{i}", None)
        if x is None or x.ndim != 2 or x.shape[0] != spec.shape[0] or x.shape[1] > spec.shape[1] \
                or x.dtype != spec.dtype:
            got = "missing" if x is None else f"{x.shape} {x.dtype}"
            raise CheckpointError(f"{path}: episode records {i} are {got}, expected {spec.dtype} rows of "
                                  f"{spec.shape[0]} with at most {spec.shape[1]} columns")
        padded = np.zeros(spec.shape, spec.dtype)
        padded[:, :x.shape[1]] = x
        data[f"leaf_{i}"] = padded
    try:
        saved = parse_json(str(data["fingerprint"]))
        impls = parse_json(str(data["key_impls"]))
        chunks_done = int(data["chunks_done"])
        if not isinstance(saved, dict) or not isinstance(impls, list) or len(impls) != len(specs):
            raise ValueError("fingerprint or key_impls malformed")
    except (KeyError, ValueError, TypeError) as err:
        raise CheckpointError(f"{path}: not a jaxrobo checkpoint ({err})") from None
    why = fingerprint_mismatch(saved, fingerprint)
    if why is not None:
        raise CheckpointError(f"{path}: refusing to resume: {why}")
    if chunks_done < 0 or (max_chunks is not None and chunks_done > max_chunks):
        bound = "" if max_chunks is None else max_chunks
        raise CheckpointError(f"{path}: chunks_done={chunks_done} is outside 0..{bound} (the run's chunks); the "
                              "checkpoint is corrupt")
    episode = next((i for i, (keypath, _) in enumerate(with_paths) if jax.tree_util.keystr(keypath) == EPISODE_LEAF),
                   None)
    if episode is not None and f"leaf_{episode}" in data and np.any(np.asarray(data[f"leaf_{episode}"]) < 0):
        raise CheckpointError(f"{path}: leaf {episode} (each env's episode count) holds negative counts; the "
                              "checkpoint is corrupt")
    leaves = []
    for i, (spec, impl) in enumerate(zip(specs, impls)):
        x = data.get(f"leaf_{i}")
        if x is None:
            raise CheckpointError(f"{path}: leaf {i} is missing")
        try:
            leaf = jax.random.wrap_key_data(x, impl=impl) if impl is not None else jnp.asarray(x)
        except (TypeError, ValueError) as err:
            raise CheckpointError(f"{path}: leaf {i} cannot be restored ({err})") from None
        if leaf.shape != spec.shape or leaf.dtype != spec.dtype:
            raise CheckpointError(f"{path}: leaf {i} is {leaf.shape} {leaf.dtype}, expected {spec.shape} "
                                  f"{spec.dtype}")
        leaves.append(leaf)
    return jax.tree.unflatten(treedef, leaves), chunks_done
