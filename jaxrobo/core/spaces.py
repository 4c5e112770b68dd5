"""Action and observation spaces, as small immutable descriptions that JAX code and the Gymnasium adapter share.
Describing a space needs no JAX; :meth:`Discrete.sample` and :meth:`Box.sample` import it."""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import jax


@dataclasses.dataclass(frozen=True)
class Discrete:
    """Integer actions ``0 .. n-1``."""

    n: int
    dtype: type = np.int32

    def sample(self, key: jax.Array) -> jax.Array:
        import jax

        return jax.random.randint(key, (), 0, self.n, dtype=self.dtype)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return x.shape == () and np.issubdtype(x.dtype, np.integer) and 0 <= int(x) < self.n


@dataclasses.dataclass(frozen=True)
class Box:
    """A real vector bounded per dimension (``inf`` where unbounded)."""

    low: np.ndarray
    high: np.ndarray
    names: tuple[str, ...] = ()
    dtype: type = np.float32

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self.low))

    def sample(self, key: jax.Array) -> jax.Array:
        import jax
        import jax.numpy as jnp

        low = jnp.where(jnp.isfinite(self.low), self.low, -1.0)
        high = jnp.where(jnp.isfinite(self.high), self.high, 1.0)
        return jax.random.uniform(key, self.shape, self.dtype, low, high)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return x.shape == self.shape and bool(np.all(x >= self.low) and np.all(x <= self.high))
