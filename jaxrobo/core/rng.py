"""Random numbers for the hot loop: bit for bit JAX's default (threefry) ``split`` / ``bits`` / ``uniform``, cheaper.

A tabular training step draws random numbers in every env every step (key split, exploration, resets), and on a CPU they
cost more than the cart-pole's physics. JAX lowers its threefry hash on CPU as a *rolled* loop (five iterations of four
rounds, to keep compile times down), so each iteration writes the whole batch of counters back to memory and XLA cannot
fuse the hash with what consumes it. Here the same hash (Threefry-2x32, 20 rounds, JAX's partitionable counter layout)
is written out unrolled in ``jnp`` ops: XLA fuses it into the surrounding loop, and the values are JAX's own, so results
do not change (tested against ``jax.random``). With the one-hash epsilon-greedy of :mod:`jaxrobo.tabular.learner` it
doubled cart-pole Q-learning's env-steps/s on 2 CPU cores. On GPUs JAX's lowering is unrolled already; the H100 still
gained (1.8x on `analytic`, all changes together).

Keys of another implementation (``jax_default_prng_impl``, ``jax.random.key(..., impl=...)``) or with
``jax_threefry_partitionable`` off fall back to ``jax.random``.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core import hash_kernel

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)


def seed_words(seeds: Any) -> np.ndarray:
    """The threefry key data of each seed, ``uint32[..., 2]``: its high and low 32-bit words (``0 <= s < 2**64``),
    written on the host. JAX's threefry seeding puts a seed's words in a key's two words, so for ``0 <= s < 2**32``
    this is ``jax.random.key_data(jax.random.key(s))`` with x64 on or off (:func:`seed_key_data`)."""
    s = np.asarray(seeds, np.uint64)
    return np.stack([(s >> np.uint64(32)).astype(np.uint32), (s & np.uint64(0xFFFFFFFF)).astype(np.uint32)], -1)


def _host_seedable(seeds: Sequence[Any]) -> bool:
    """Whether :func:`seed_words` gives ``jax.random.key``'s data for every one of ``seeds``: integers in
    ``[0, 2**32)`` under JAX's default threefry implementation and no ``jax_random_seed_offset``."""
    return all(isinstance(s, (int, np.integer)) and not isinstance(s, bool) and 0 <= s < 2**32 for s in seeds) \
        and jax.config.jax_default_prng_impl == "threefry2x32" and not getattr(jax.config, "jax_random_seed_offset", 0)


def seed_key_data(seeds: Sequence[Any]) -> np.ndarray:
    """``jax.random.key_data(jax.random.key(s))`` of each seed, stacked on the host (a sweep's rows): written by
    :func:`seed_words` where :func:`_host_seedable`, else each by ``jax.random.key`` itself."""
    if _host_seedable(seeds):
        return seed_words([int(s) for s in seeds])
    return np.stack([np.asarray(jax.random.key_data(jax.random.key(s))) for s in seeds])


def seed_key(seed: int) -> jax.Array:
    """``jax.random.key(seed)``, the same key, written on the host where :func:`_host_seedable`: no program compiled
    or run. ``jax.random.key`` computes it on the device, two small programs compiled on first use (0.10-0.15 s of
    a GPU command's start-up with an empty cache) and dispatched every call. Any other seed, default
    implementation or seed offset is ``jax.random.key``'s own (tested against it)."""
    if _host_seedable([seed]):
        return jax.random.wrap_key_data(seed_words(int(seed)), impl="threefry2x32")
    return jax.random.key(seed)


def threefry2x32(k1: jax.Array, k2: jax.Array, x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Threefry-2x32 (Salmon et al. 2011, 20 rounds) of counters ``(x1, x2)`` under key ``(k1, k2)``: uint32 arrays
    of one shape, or scalars (a Pallas kernel hashes its ``[block]`` vectors of key words with it)."""
    ks = (k1, k2, k1 ^ k2 ^ _PARITY)
    x1, x2 = x1 + ks[0], x2 + ks[1]
    for block in range(5):
        for r in _ROTATIONS[block % 2]:
            x1 = x1 + x2
            x2 = (x2 << np.uint32(r)) | (x2 >> np.uint32(32 - r))
            x2 = x1 ^ x2
        x1 = x1 + ks[(block + 1) % 3]
        x2 = x2 + ks[(block + 2) % 3] + np.uint32(block + 1)
    return x1, x2


#: :func:`threefry2x32` jitted on its own, for the draws below: JAX traces its 20 rounds once per shape of counters
#: instead of at every draw a program makes (each trace about a hundred ``jnp`` ops), and XLA inlines the call, so the
#: fused code and its bits are the same. (A Pallas kernel hashes with :func:`threefry2x32` itself.)
_hash_ops = jax.jit(threefry2x32)
#: The same hash as one call of jaxlib's GPU kernel (:mod:`jaxrobo.core.hash_kernel`), where the plan traces with it.
_hash_call = jax.jit(hash_kernel.threefry2x32)


def _hash(k1: jax.Array, k2: jax.Array, x1: jax.Array, x2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """:func:`threefry2x32` for the draws below: the kernel where the plan traces with it, else the ops (the same bits
    either way)."""
    return (_hash_call if hash_kernel.wanted() else _hash_ops)(k1, k2, x1, x2)


def _words(key: jax.Array) -> tuple[jax.Array, jax.Array] | None:
    """The two key words of a threefry key, or None where this module must defer to ``jax.random``."""
    if not jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) or key.ndim:
        return None
    if str(jax.random.key_impl(key)) != "threefry2x32" or not jax.config.jax_threefry_partitionable:
        return None
    data = jax.random.key_data(key)
    return data[0], data[1]


def _hash_counters(words: tuple[jax.Array, jax.Array], shape: tuple[int, ...]) -> tuple[jax.Array, jax.Array]:
    """The hash of counters ``0 .. prod(shape) - 1`` laid out in ``shape`` (JAX's partitionable layout)."""
    size = math.prod(shape)
    if size >= 2**32:
        raise ValueError(f"at most 2**32 - 1 random words per draw, asked for {size}")
    lo = jax.lax.iota(jnp.uint32, size).reshape(shape) if size else jnp.zeros(shape, jnp.uint32)
    return _hash(words[0], words[1], jnp.zeros(shape, jnp.uint32), lo)


def split(key: jax.Array, num: int = 2) -> jax.Array:
    """``num`` new keys from ``key``; equal to ``jax.random.split(key, num)``."""
    words = _words(key)
    if words is None:
        return jax.random.split(key, num)
    x1, x2 = _hash_counters(words, (num,))
    return jax.random.wrap_key_data(jnp.stack([x1, x2], axis=-1), impl=jax.random.key_impl(key))


def subkey(key: jax.Array, index: int, num: int) -> jax.Array:
    """``jax.random.split(key, num)[index]`` alone, without hashing the others (unused ones cost nothing)."""
    if not 0 <= index < num:
        raise ValueError(f"index must be in [0, {num}), got {index}")
    words = _words(key)
    if words is None:
        return jax.random.split(key, num)[index]
    x1, x2 = _hash(words[0], words[1], jnp.uint32(0), jnp.uint32(index))
    return jax.random.wrap_key_data(jnp.stack([x1, x2]), impl=jax.random.key_impl(key))


def bits(key: jax.Array, shape: tuple[int, ...] = ()) -> jax.Array:
    """uint32 random bits of ``shape``; equal to ``jax.random.bits(key, shape, jnp.uint32)``."""
    words = _words(key)
    if words is None:
        return jax.random.bits(key, shape, jnp.uint32)
    x1, x2 = _hash_counters(words, tuple(shape))
    return x1 ^ x2


def unit_float(words: jax.Array) -> jax.Array:
    """float32 in ``[0, 1)`` from uint32 random words: the 23 high bits as a mantissa in ``[1, 2)``, minus 1."""
    return jax.lax.bitcast_convert_type((words >> 9) | jnp.uint32(0x3F800000), jnp.float32) - 1.0


def uniform_pair(key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Two float32 uniforms in ``[0, 1)`` from one hash (both of its output words; ``bits`` keeps their xor)."""
    words = _words(key)
    if words is None:
        u = unit_float(jax.random.bits(key, (2,), jnp.uint32))
        return u[0], u[1]
    x1, x2 = _hash(words[0], words[1], jnp.uint32(0), jnp.uint32(0))
    return unit_float(x1), unit_float(x2)


def uniform(key: jax.Array, shape: tuple[int, ...] = (), low: float | jax.Array = 0.0,
            high: float | jax.Array = 1.0) -> jax.Array:
    """float32 uniform in ``[low, high)``; equal to ``jax.random.uniform(key, shape, float32, low, high)``.

    JAX's own recipe (:func:`unit_float`, scaled), without its final clamp to ``low`` (which an in-range float
    never needs)."""
    unit = unit_float(bits(key, shape))
    low = jnp.asarray(low, jnp.float32)
    return unit * (jnp.asarray(high, jnp.float32) - low) + low


def bernoulli(key: jax.Array, p: float | jax.Array = 0.5, shape: tuple[int, ...] = ()) -> jax.Array:
    """True with probability ``p``; equal to ``jax.random.bernoulli(key, float32(p), shape)``."""
    return uniform(key, shape) < jnp.asarray(p, jnp.float32)
