"""Action and observation spaces, as small immutable descriptions that JAX code and the Gymnasium adapter share."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Discrete:
    """Integer actions ``0 .. n-1``."""

    n: int
    dtype: type = jnp.int32

    def sample(self, key: jax.Array) -> jax.Array:
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
    dtype: type = jnp.float32

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self.low))

    def sample(self, key: jax.Array) -> jax.Array:
        low = jnp.where(jnp.isfinite(self.low), self.low, -1.0)
        high = jnp.where(jnp.isfinite(self.high), self.high, 1.0)
        return jax.random.uniform(key, self.shape, self.dtype, low, high)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return x.shape == self.shape and bool(np.all(x >= self.low) and np.all(x <= self.high))
