"""jaxrobo computes in JAX's default 32-bit precision; 64-bit mode (``jax_enable_x64``) is refused up front.

The environments, physics backends and learners carry float32/int32 state through ``lax.scan`` loops. With
x64 on, Python scalars and fresh arrays become float64/int64 while other parts of the carry stay 32-bit, and the
loops fail deep inside tracing ("scan carry types differ"). Rather than a traceback from the middle of a
compile, :func:`check_precision` raises :class:`jaxrobo.ConfigError` at the boundary (``jaxrobo.make``, which
the trainer, the sweep, the Gymnasium adapter and the CLI all go through) saying what is on and how to turn
it off.
"""
from __future__ import annotations

import os

from jaxrobo.core.config import ConfigError


def x64_enabled() -> bool:
    """Whether JAX's 64-bit mode is on in this thread (environment variable, flag or ``jax.config.update``)."""
    import jax

    return bool(jax.config.jax_enable_x64)


def check_precision(where: str = "jaxrobo") -> None:
    """Raise :class:`ConfigError` when JAX's 64-bit mode is on; jaxrobo runs in 32-bit only."""
    if not x64_enabled():
        return
    env_value = os.environ.get("JAX_ENABLE_X64")
    if env_value is not None:
        source = f"the environment variable JAX_ENABLE_X64={env_value}"
        fix = "unset JAX_ENABLE_X64 (or set JAX_ENABLE_X64=0) before starting Python"
    else:
        source = "jax.config.update('jax_enable_x64', True) or the --jax_enable_x64 flag"
        fix = "call jax.config.update('jax_enable_x64', False) before using jaxrobo"
    raise ConfigError(f"{where}: JAX 64-bit mode is on (jax_enable_x64=True, from {source}); jaxrobo's "
                      f"environments and learners run in 32-bit only: {fix}")
