"""The MJX stage replacement: one stage of ``mjx.step`` in a form XLA compiles better, the same values bit for bit.

MJX's ``smooth.com_pos`` computes the body inertias about the subtree centres of mass (``cinert``) and takes the upper
triangle of each 3x3 inertia with an index-array gather. XLA fuses the 3x3 matrix products into that gather and
recomputes them for each of the six entries it reads, and on a GPU at large batches that gather was a large share of a
cart-pole step (docs/results.md, ``env_groups.json``). :func:`lean` replaces ``com_pos`` while MJX code is traced inside
it by MJX's own ``com_pos`` followed by ``cinert`` computed again with the triangle taken by static indices: the same
arithmetic in the same order, so the same values bit for bit (``tests/test_mjx_lean.py`` checks positions, velocities
and ``cinert`` of both robots on random states), and XLA drops MJX's own ``cinert`` as dead code.

It reaches into MJX's private modules, so it is guarded: it applies only to ``mujoco-mjx`` versions in
:data:`WRITTEN_FOR` (the range it was written and tested for) with the layout it expects. Elsewhere it does
nothing, MJX runs as it is (the same values, maybe slower), and the first :func:`lean` block that asked for it
says why once with a :class:`RuntimeWarning`; :func:`unavailable` returns the reason. To widen the range, run
``tests/test_mjx_lean.py`` on the new version.

How the choice reaches the physics. The choice belongs to the run's :class:`jaxrobo.speed.plan.ExecutionPlan`, but the
MJX step is deep under the pure ``env.step(state, action, params)``, whose signature should not carry speed
choices. So it travels with tracing, not with the values: :func:`choose` sets the choice for a block (a
``contextvars.ContextVar``, so threads and asyncio tasks each see their own; ``ExecutionPlan.tracing`` enters it),
:func:`wanted` reads it (True where no block set it: lean MJX is the default), and the simulator traces each MJX
step inside ``lean(wanted())``. Since the choice acts while tracing, a function jitted and traced once keeps the
choice it was traced with; JAX's persistent cache keys on the lowered program, which differs with the choice.

Public surface: :func:`lean`, :func:`choose`, :func:`wanted`, :func:`unavailable`, :data:`WRITTEN_FOR`.
Everything with a leading underscore is private (it follows MJX's internals).
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import importlib
import io
import warnings
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp

from jaxrobo.core.version import outside, warn_once
from jaxrobo.physics.mjx_import import import_mjx, installed_version


class LazyModule:
    """A module imported on first attribute access, silently (MJX reports on import that Warp is missing, and
    importing it takes seconds: a command that never steps MJX, such as ``jaxrobo list``, never pays for it)."""

    def __init__(self, name: str):
        self._name = name
        self._module: Any = None

    def load(self) -> Any:
        if self._module is None:
            with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), \
                    contextlib.redirect_stderr(io.StringIO()):
                warnings.filterwarnings("ignore", message=".*warp.*")
                warnings.filterwarnings("ignore", message=".*not actively being maintained.*")
                if self._name.startswith("mujoco.mjx"):
                    import_mjx()  # without its mesh libraries, which jaxrobo's robots never call
                self._module = importlib.import_module(self._name)
        return self._module

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.load(), attr)


#: ``mujoco.mjx`` and the MJX internals whose com_pos stage this replaces (without them MJX runs as it is).
mjx = LazyModule("mujoco.mjx")
_mjx_math = LazyModule("mujoco.mjx._src.math")
_mjx_smooth = LazyModule("mujoco.mjx._src.smooth")


def _internal(module: LazyModule | None, attr: str) -> bool:
    if module is None:
        return False
    try:
        return hasattr(module.load(), attr)
    except ImportError:  # pragma: no cover - another MJX layout
        return False

#: The ``mujoco-mjx`` versions the replacement was written and tested for: ``[low, high)`` as (major, minor).
WRITTEN_FOR = ((3, 17), (3, 18))
#: The upper triangle of a 3x3 inertia, in the order of MJX's ``cinert`` (xx, yy, zz, xy, xz, yz).
_TRIU = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))

_WANTED: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxrobo_mjx_lean", default=True)
_WARNED: set[str] = set()


def unavailable() -> str | None:
    """Why :func:`lean` cannot replace the stage here (a sentence), or None when it can."""
    version = installed_version()
    reason = outside("mujoco-mjx", version, WRITTEN_FOR)
    if reason:
        return reason
    if not (_internal(_mjx_smooth, "com_pos") and _internal(_mjx_math, "matmul_unroll") and _internal(mjx, "Impl")):
        return f"mujoco-mjx {version} does not have the internals it replaces (smooth.com_pos, math.matmul_unroll)"
    return None


def _com_pos_static_triu(com_pos: Callable, m: Any, d: Any) -> Any:
    """MJX's ``smooth.com_pos`` (``com_pos``), with the body inertias ``cinert`` computed again with their upper
    triangle taken by static indices (see the module docstring). Models on another MJX implementation (Warp)
    pass through."""
    d = com_pos(m, d)
    if m.impl != mjx.Impl.JAX:
        return d
    offset = d.xipos - d.subtree_com[m.body_rootid]

    def inert_com(inertia, ximat, off, mass):
        h = jnp.cross(off, -jnp.eye(3))
        inert = _mjx_math.matmul_unroll(ximat * inertia, ximat.T)
        inert += _mjx_math.matmul_unroll(h, h.T) * mass
        triu = jnp.stack([inert[i, j] for i, j in _TRIU])
        return jnp.concatenate([triu, off * mass, mass[None]])

    cinert = jax.vmap(inert_com)(m.body_inertia, d.ximat, offset, m.body_mass)
    return d.tree_replace({"_impl.cinert": cinert})


@contextlib.contextmanager
def lean(enabled: bool = True) -> Iterator[None]:
    """While tracing MJX code inside this block, ``mjx.step``/``mjx.forward`` compute the body inertias with the
    replacement (``enabled``), or as MJX has them (not ``enabled``: the block does nothing). It swaps MJX's
    ``smooth.com_pos`` for the block's duration only, so MJX code traced elsewhere (Brax's pipelines, another
    library) is untouched; a thread tracing MJX at the same time would get the same values either way. Nested
    blocks swap once. Where :func:`unavailable` gives a reason, a no-op that warns once."""
    if not enabled:
        yield
        return
    reason = unavailable()
    if reason is not None:
        warn_once(_WARNED, f"jaxrobo.physics.mjx_lean: MJX runs as it is: {reason}", stacklevel=4)
        yield
        return
    smooth = _mjx_smooth.load()
    if getattr(smooth.com_pos, "jaxrobo_lean", False):  # an outer block swapped it already
        yield
        return
    original = smooth.com_pos
    replacement = functools.partial(_com_pos_static_triu, original)
    replacement.jaxrobo_lean = True
    smooth.com_pos = replacement
    try:
        yield
    finally:
        smooth.com_pos = original


def wanted() -> bool:
    """Whether MJX code traced now should use :func:`lean`: the innermost :func:`choose` block's choice, True
    outside any."""
    return _WANTED.get()


@contextlib.contextmanager
def choose(enabled: bool) -> Iterator[None]:
    """Within this block (this thread or task), :func:`wanted` returns ``enabled``."""
    token = _WANTED.set(bool(enabled))
    try:
        yield
    finally:
        _WANTED.reset(token)
