"""A large run's summary figures and episode statistics take their per-env and per-column parts from the device.

At the end of a run the records are ``[n_envs, episodes]`` arrays on the device; the host used to sort and partition
them for the summary's figures (each env's 100 longest episodes, its best 100-episode window) and for
``episode_stats.csv``'s percentiles (every episode column's order statistics over a million envs): most of the CPU
a 1,048,576-env run's writing took on an H200 host. :func:`parts` computes those parts where the records are, in
one program compiled in a thread while the run trains (:class:`Prepared`) and run in another while the records
cross to the host after the evaluation; only the parts cross with them.

Every part is exact: maxima, integer sums of whole-number lengths, returns gathered as they are, values picked
at ranks from sorted columns. Every sum over envs stays on the host, in numpy's order
(:meth:`jaxrobo.training.summary.TrainResult.summary`, :func:`jaxrobo.io.results.episode_stats`), so the figures
and the statistics are the same floats whichever side computed their parts, on any number of devices
(tests/test_record_parts.py compares them bit for bit). Used where it pays (:func:`wanted`): a large run on an
accelerator, in one process.
"""
from __future__ import annotations

import functools
import threading
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.io.results import PERCENTILES
from jaxrobo.training.summary import BEST  # the seed's "best 100": one home

#: Record entries (envs x episode slots) from which the device computes the parts: below it the host's numpy is
#: as quick as a program's dispatch and copy (65,536 envs x 64 slots is 4 M).
MIN_ENTRIES = 1 << 22



def wanted(n_envs: int, slots: int, max_length: int, *, backend: str | None = None) -> bool:
    """Whether a run of ``n_envs`` x ``slots`` records (episodes of at most ``max_length`` steps) takes its parts
    from the device: large enough (:data:`MIN_ENTRIES`), not on a CPU device (there numpy is that device), one
    process (the records are gathered from every process otherwise), and the sums of an env's lengths (and the
    envs of a column) within int32."""
    backend = jax.default_backend() if backend is None else backend
    return (n_envs * slots >= MIN_ENTRIES and backend != "cpu" and jax.process_count() == 1
            and slots * max(int(max_length), 1) < 2 ** 31 and n_envs < 2 ** 31)


def parts(returns: jax.Array, lengths: jax.Array, episode: jax.Array, *, higher: bool) -> dict[str, jax.Array]:
    """The exact parts of the figures and statistics (traceable). ``returns`` / ``lengths``: ``[n_envs, slots]``,
    env ``e``'s first ``min(episode[e], slots)`` slots recorded; ``higher``: the direction of the best window.

    - ``highest``: each env's highest recorded return (-inf with none, NaN where one is NaN);
    - ``top_sum``: the sum of its ``min(BEST, count)`` longest recorded lengths; ``length_sum``: of all of them;
    - ``window_sum``: its best ``BEST``-episode window's length sum (the highest, or lowest with ``higher``
      False), all of its lengths where it recorded fewer;
    - ``last_returns``: ``[n_envs, min(BEST, slots)]``, its last ``min(BEST, count)`` returns first, in order (a
      gather the host did in 0.7-2.7 s of a 1 M-env run's writing; 0.4 GB to copy);
    - ``order_returns`` / ``order_lengths``: ``[2 * len(PERCENTILES), slots]``, each column's values at the ranks
      of :func:`jaxrobo.io.results.percentile_ranks` among its recorded entries (:func:`column_ranks`), unrecorded
      ones sorted last (NaN, or the largest integer)."""
    n_envs, slots = returns.shape
    count = jnp.minimum(episode, slots).astype(jnp.int32)
    mask = jnp.arange(slots)[None, :] < count[:, None]
    int_min, int_max = jnp.iinfo(lengths.dtype).min, jnp.iinfo(lengths.dtype).max
    k_top = min(BEST, slots)
    top = jnp.sort(jnp.where(mask, lengths, int_min), axis=1)[:, slots - k_top:]
    recorded = jnp.where(mask, lengths, 0)
    length_sum = recorded.sum(axis=1)
    k = jnp.minimum(count, BEST)
    last = jnp.take_along_axis(returns, jnp.clip(count[:, None] - k[:, None] + jnp.arange(k_top)[None, :], 0,
                                                 slots - 1), axis=1)
    window_sum = length_sum
    if slots >= BEST:
        prefix = jnp.concatenate([jnp.zeros((n_envs, 1), recorded.dtype), jnp.cumsum(recorded, axis=1)], axis=1)
        sums = prefix[:, BEST:] - prefix[:, :-BEST]  # the window ending at slot BEST + i
        inside = jnp.arange(sums.shape[1])[None, :] <= (count - BEST)[:, None]
        best = (jnp.where(inside, sums, int_min).max(axis=1) if higher
                else jnp.where(inside, sums, int_max).min(axis=1))
        window_sum = jnp.where(count >= BEST, best, length_sum)
    ranks = column_ranks(mask.sum(axis=0, dtype=jnp.int32))

    def order(x: jax.Array, pad: Any) -> jax.Array:  # sorted columns, an env per entry along the minor axis
        columns = jnp.sort(jnp.where(mask, x, pad).T, axis=1)
        return jnp.take_along_axis(columns, ranks.T, axis=1).T

    nan = jnp.isnan(returns) & mask  # numpy's maximum is NaN where a NaN is among its numbers: said, not left to XLA
    highest = jnp.where(nan.any(axis=1), jnp.nan, jnp.where(mask & ~nan, returns, -jnp.inf).max(axis=1))
    return {"highest": highest, "top_sum": jnp.where(top != int_min, top, 0).sum(axis=1),
            "length_sum": length_sum, "window_sum": window_sum, "last_returns": last,
            "order_returns": order(returns, jnp.nan), "order_lengths": order(lengths, int_max)}


def column_ranks(count: jax.Array) -> jax.Array:
    """``[2 * len(PERCENTILES), columns]`` int32 (traceable): the ranks :func:`jaxrobo.io.results.percentile_ranks`
    gives for columns of ``count`` entries (those of empty columns: 0), in whole numbers: ``floor((count - 1) * q /
    100)`` is the floor of numpy's float64 position for every count (``q / 100.0`` rounds up for 10 and 90, and
    the product's rounding never crosses a whole number), computed without overflow."""
    last = jnp.maximum(count - 1, 0)
    lo = [last // 100 * q + last % 100 * q // 100 for q in PERCENTILES]
    hi = [jnp.minimum(r + 1, last) for r in lo]
    return jnp.stack(lo + hi).astype(jnp.int32)


@functools.lru_cache(maxsize=8)
def _program(higher: bool) -> Any:
    return jax.jit(functools.partial(parts, higher=higher))


class Prepared:
    """:func:`parts` compiled in a thread for a carry's record shapes (and shardings) while the run trains, then
    computed and copied to the host in a thread (:meth:`start`) while the caller copies the records
    (:meth:`result`): the program's first call allocates its temporaries and waits for them (about a second of
    the caller's at 1 M envs on an H200)."""

    def __init__(self, returns: Any, lengths: Any, episode: Any, *, higher: bool):
        def shape(x: Any) -> jax.ShapeDtypeStruct:
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))

        self.higher = higher
        self._inputs = (shape(returns), shape(lengths), shape(episode))
        self._compiled: list = []
        self._out: list = []
        self.computing: threading.Thread | None = None
        self.thread = threading.Thread(target=self._compile, name="jaxrobo-compile-record-parts", daemon=True)
        self.thread.start()

    def _compile(self) -> None:
        try:
            self._compiled.append(_program(self.higher).lower(*self._inputs).compile())
        except Exception:  # noqa: BLE001 - start() compiles again and says why where it fails
            pass

    def start(self, returns: jax.Array, lengths: jax.Array, episode: jax.Array) -> Prepared:
        """Compute the parts of these records and copy them to the host, in a thread."""
        def work() -> None:
            self.thread.join()
            try:
                out = (self._compiled[0] if self._compiled else _program(self.higher))(returns, lengths, episode)
                self._out.append(jax.device_get(out))
            except Exception as err:  # noqa: BLE001 - the host computes the same figures without them
                self._out.append(err)

        self.computing = threading.Thread(target=work, name="jaxrobo-record-parts", daemon=True)
        self.computing.start()
        return self

    def result(self) -> dict[str, np.ndarray] | None:
        """The parts as host arrays, once computed; None (with a warning) where they could not be: the summary and
        the statistics are then computed from the records, the same numbers, more slowly."""
        self.computing.join()
        out = self._out[0] if self._out else RuntimeError("the thread ended without a result")
        if isinstance(out, Exception):
            import warnings

            warnings.warn(f"the records' parts were not computed on the device ({out!r}); the host computes "
                          "the summary and the statistics from the records", RuntimeWarning, stacklevel=2)
            return None
        return out
