"""Observation → integer state index, for tabular learners.

Each observation dimension is cut into equal bins between a low and a high bound (values outside are clipped
into the end bins); the per-dimension bin indices are combined row-major into one index in
``[0, n_states)``. Three ways to give the bins, one mechanism:

* ``bins``   - ``number_splits`` bins per dimension (or a list, one count per dimension) over ``[low, high]``;
* ``round``  - the seed's mode: one bin per multiple of ``resolution`` (0.1) in ``[low, high]``, so an
  observation rounded to 0.1 maps to its own state, as the seed's string keys did;
* ``edges``  - explicit interior bin edges per dimension (uneven bins, e.g. finer near upright).
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core.struct import pytree_dataclass, static_field

MODES = ("bins", "round", "edges")


@pytree_dataclass
class Discretiser:
    """``low`` and ``width`` are traced (sweepable); ``bins`` (the table shape) and ``edges`` are static."""

    low: jax.Array
    width: jax.Array
    bins: tuple[int, ...] = static_field()
    edges: tuple[tuple[float, ...], ...] | None = static_field(default=None)

    @property
    def n_states(self) -> int:
        return int(math.prod(self.bins))

    def bin_indices(self, obs: jax.Array) -> jax.Array:
        """Per-dimension bin index of ``obs``."""
        obs = jnp.asarray(obs, jnp.float32)
        bins = jnp.asarray(self.bins, jnp.int32)
        if self.edges is not None:
            idx = jnp.stack([jnp.sum(obs[i] >= jnp.asarray(e, jnp.float32)) for i, e in enumerate(self.edges)])
            return idx.astype(jnp.int32)
        idx = jnp.floor((obs - self.low) / self.width).astype(jnp.int32)
        return jnp.clip(idx, 0, bins - 1)

    def __call__(self, obs: jax.Array) -> jax.Array:
        """The state index of one observation (vmap for a batch)."""
        idx = self.bin_indices(obs)
        strides = np.cumprod((self.bins[1:] + (1,))[::-1])[::-1].astype(np.int32)
        return jnp.sum(idx * jnp.asarray(strides)).astype(jnp.int32)


#: Most states a table may have: state indices are int32 (``Discretiser.__call__``), and a table this size already
#: takes 8 GiB per action and table, far past what any batch of them fits in.
MAX_STATES = 2**31 - 1

#: The names :func:`make_discretiser`'s arguments have in messages; :func:`jaxrobo.training.run.resolve` passes the
#: TrainConfig field names instead (``state_low``, ``bins``, ...), so each message names what the user set.
ARG_NAMES = {"low": "low", "high": "high", "mode": "mode", "splits": "number_splits", "resolution": "resolution",
             "edges": "edges"}


def _is_integral(x: object) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float, np.integer, np.floating)) and float(x).is_integer()


def _show(x: object) -> str:
    """A value as the user wrote it: lists (tuples once validated) print as lists."""
    if isinstance(x, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_show(v) for v in x) + "]"
    return repr(x.item() if isinstance(x, np.generic) else x)


def _is_seq(x: object) -> bool:
    return isinstance(x, (list, tuple)) or (isinstance(x, np.ndarray) and x.ndim == 1)


def _is_number(x: object) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float, np.integer, np.floating))


def _vector(value: object, name: str, dims: int | None, other: str = "") -> np.ndarray:
    """A 1-D list of finite numbers (``dims`` long when given), else ValueError naming ``name``."""
    if not _is_seq(value) or not all(_is_number(x) for x in value):
        raise ValueError(f"{name}={_show(value)}: expected a list of numbers, one per observation dimension"
                         + (f" ({dims})" if dims is not None else ""))
    arr = np.asarray(value, np.float64)
    if dims is not None and arr.shape[0] != dims:
        raise ValueError(f"{name}={_show(value)}: expected {dims} values, one per observation dimension, "
                         f"got {arr.shape[0]}" + (f" ({other} and {name} must be equal-length lists)" if other else ""))
    if arr.shape[0] == 0:
        raise ValueError(f"{name}=[]: expected at least one value")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}={_show(value)}: every value must be finite")
    with np.errstate(over="ignore"):
        in_float32 = arr.astype(np.float32)
    if not np.all(np.isfinite(in_float32)):  # the bounds are float32 arrays in the run
        raise ValueError(f"{name}={_show(value)}: a value is inf in float32 (magnitude above 3.4e38)")
    return arr


def check(low: Sequence[float], high: Sequence[float], mode: str = "bins", number_splits: int | Sequence[int] = 10,
          resolution: float = 0.1, edges: Sequence[Sequence[float]] | None = None, dims: int | None = None,
          names: dict[str, str] | None = None) -> tuple[np.ndarray, np.ndarray, tuple[int, ...],
                                                         tuple[tuple[float, ...], ...] | None]:
    """Validate discretiser settings with plain numpy (nothing on a device): ``(low, high, bins, edges)``.

    Raises ``ValueError`` naming the field (as ``names`` calls it) and what it accepts. ``dims``: the
    observation's length, when known, which every per-dimension list must match.
    """
    n = {**ARG_NAMES, **(names or {})}
    if mode not in MODES:
        raise ValueError(f"{n['mode']}={mode!r}: allowed values are {', '.join(MODES)}")
    low_np = _vector(low, n["low"], dims)
    dims = low_np.shape[0]
    high_np = _vector(high, n["high"], dims, other=n["low"])
    if mode != "edges":
        bad = [i for i in range(dims) if not high_np[i] > low_np[i]]
        if bad:
            i = bad[0]
            raise ValueError(f"{n['high']}[{i}]={high_np[i]:g} must be greater than {n['low']}[{i}]={low_np[i]:g} "
                             f"(each dimension needs {n['high']} > {n['low']})")
    edges_t = None
    if mode == "edges":
        if not _is_seq(edges) or len(edges) != dims:
            got = "none" if edges is None else _show(edges)
            raise ValueError(f"{n['mode']}='edges' needs {n['edges']}: one list of edges per dimension "
                             f"({dims} lists of interior bin edges), got {got}")
        out = []
        for i, e in enumerate(edges):
            if not _is_seq(e) or not all(_is_number(x) for x in e):
                raise ValueError(f"{n['edges']}[{i}]={_show(e)}: expected a list of numbers (the interior bin edges)")
            e = tuple(float(x) for x in e)
            if not all(math.isfinite(x) and abs(x) <= np.finfo(np.float32).max for x in e):
                raise ValueError(f"{n['edges']}[{i}]={list(e)}: every edge must be finite (in float32 too)")
            if any(b <= a for a, b in zip(e, e[1:])):
                raise ValueError(f"{n['edges']}[{i}]={list(e)}: edges must be strictly increasing")
            out.append(e)
        edges_t = tuple(out)
        bins = tuple(len(e) + 1 for e in edges_t)
    elif mode == "round":
        if not (_is_number(resolution) and math.isfinite(resolution) and resolution > 0):
            raise ValueError(f"{n['resolution']}={resolution!r}: expected a finite number > 0")
        counts = np.round(high_np / resolution) - np.round(low_np / resolution) + 1
        if np.any(counts > MAX_STATES):
            raise ValueError(f"{n['resolution']}={resolution!r}: gives {counts.max():.3g} bins in one dimension "
                             f"(at most {MAX_STATES} states); use a coarser resolution")
        bins = tuple(int(c) for c in counts)
    else:
        many = _is_seq(number_splits)
        if not (many or _is_number(number_splits)):
            raise ValueError(f"{n['splits']}={_show(number_splits)}: expected a positive integer or one per dimension "
                             f"({dims})")
        splits = list(number_splits) if many else [number_splits] * dims
        if len(splits) != dims:
            raise ValueError(f"{n['splits']}={_show(splits)}: expected {dims} bin counts, one per observation "
                             f"dimension, got {len(splits)}")
        for i, c in enumerate(splits):
            if not _is_integral(c) or c < 1:
                at = f"[{i}]" if many else ""
                raise ValueError(f"{n['splits']}{at}={_show(c)}: expected an integer >= 1 (bins in that dimension)")
        bins = tuple(int(c) for c in splits)
    total = math.prod(bins)
    if total > MAX_STATES:
        what = (f"{n['edges']}" if mode == "edges" else f"{n['resolution']}={resolution!r}" if mode == "round"
                else f"{n['splits']}={_show(number_splits)}")
        raise ValueError(f"{what}: {' x '.join(map(str, bins))} = {total:.3g} states, more than the {MAX_STATES} a "
                         f"table may have (state indices are int32); use fewer bins")
    return low_np, high_np, bins, edges_t


def make_discretiser(low: Sequence[float], high: Sequence[float], mode: str = "bins",
                     number_splits: int | Sequence[int] = 10, resolution: float = 0.1,
                     edges: Sequence[Sequence[float]] | None = None) -> Discretiser:
    """Build a discretiser; raises ``ValueError`` naming the bad field (see :func:`check`)."""
    low_np, high_np, bins, edges_t = check(low, high, mode, number_splits, resolution, edges)
    dims = low_np.shape[0]
    # Cast on the host, then put on the device: a cast (or jnp.asarray's copy) in JAX is a program to compile.
    f32 = lambda x: jax.device_put(np.asarray(x, np.float32))  # noqa: E731
    if mode == "edges":
        return Discretiser(f32(low_np), f32(np.ones(dims)), bins, edges_t)
    if mode == "round":
        first = np.round(low_np / resolution)
        start = (first - 0.5) * resolution
        width = np.full(dims, resolution)
        return Discretiser(f32(start), f32(width), bins)
    width = (high_np - low_np) / np.asarray(bins)
    return Discretiser(f32(low_np), f32(width), bins)


def make_discretiser_for(env: Any, config: Any, env_params: Any = None) -> Discretiser:
    """The discretiser a config (a :class:`jaxrobo.training.trainer.TrainConfig`) asks for, over ``env``'s state bounds
    (``env.state_bounds``) unless the config gives its own."""
    low, high = env.state_bounds(env_params)
    low = np.asarray(config.state_low if config.state_low is not None else low, np.float64)
    high = np.asarray(config.state_high if config.state_high is not None else high, np.float64)
    splits = config.bins if config.bins is not None else config.number_splits
    return make_discretiser(low, high, config.discretiser, splits, config.resolution, config.edges)
