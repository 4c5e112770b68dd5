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
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.struct import pytree_dataclass, static_field

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


def make_discretiser(low: Sequence[float], high: Sequence[float], mode: str = "bins",
                     number_splits: int | Sequence[int] = 10, resolution: float = 0.1,
                     edges: Sequence[Sequence[float]] | None = None) -> Discretiser:
    """Build a discretiser; raises ``ValueError`` naming the bad field."""
    low_np, high_np = np.asarray(low, np.float64), np.asarray(high, np.float64)
    dims = low_np.shape[0]
    if mode not in MODES:
        raise ValueError(f"discretiser mode={mode!r}: allowed values are {', '.join(MODES)}")
    if low_np.shape != high_np.shape or low_np.ndim != 1:
        raise ValueError(f"discretiser low/high must be equal-length lists, got {low_np.shape} and {high_np.shape}")
    if not (np.all(np.isfinite(low_np)) and np.all(np.isfinite(high_np)) and np.all(high_np > low_np)):
        raise ValueError(f"discretiser bounds must be finite with high > low, got low={low_np} high={high_np}")
    if mode == "edges":
        if edges is None or len(edges) != dims:
            raise ValueError(f"discretiser mode='edges' needs one list of edges per dimension ({dims})")
        edges_t = tuple(tuple(float(x) for x in e) for e in edges)
        for i, e in enumerate(edges_t):
            if list(e) != sorted(e):
                raise ValueError(f"discretiser edges[{i}] must be increasing, got {list(e)}")
        bins = tuple(len(e) + 1 for e in edges_t)
        return Discretiser(jnp.asarray(low_np, jnp.float32), jnp.ones(dims, jnp.float32), bins, edges_t)
    if mode == "round":
        if not resolution > 0:
            raise ValueError(f"discretiser resolution={resolution}: must be > 0")
        first = np.round(low_np / resolution)
        bins = tuple(int(n) for n in np.round(high_np / resolution) - first + 1)
        start = (first - 0.5) * resolution
        width = np.full(dims, resolution)
        return Discretiser(jnp.asarray(start, jnp.float32), jnp.asarray(width, jnp.float32), bins)
    splits = [number_splits] * dims if np.ndim(number_splits) == 0 else list(number_splits)
    if len(splits) != dims or any(int(n) != n or n < 1 for n in splits):
        raise ValueError(f"number_splits={number_splits!r}: need a positive integer or one per dimension ({dims})")
    bins = tuple(int(n) for n in splits)
    width = (high_np - low_np) / np.asarray(bins)
    return Discretiser(jnp.asarray(low_np, jnp.float32), jnp.asarray(width, jnp.float32), bins)
