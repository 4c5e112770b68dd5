"""libdevice's ``sinf`` and ``cosf`` written out for small arguments, for the Pallas kernels on a GPU: the same values.

A Pallas kernel's ``jnp.sin`` and ``jnp.cos`` compile (through Triton) to calls of CUDA's libdevice ``__nv_sinf`` and
``__nv_cosf``. Each call reduces its argument by pi/2 (a rounding multiply, a float-to-int conversion, three fmas and
a check for the slow path beyond 105,615), then evaluates one of two polynomials chosen by the quadrant's parity
(selects) and flips the sign by the quadrant. Where ``fl(|t| * 2/pi) < 0.5`` the quadrant is 0 and the reduction
returns ``t`` itself (``fma(0, c, t) == t``), so the two calls are two short fma chains that can share ``t*t``;
:func:`sincos` is those chains as inline PTX ``fma.rn.f32`` in libdevice's order with libdevice's coefficients, for
``|t| <= LIMIT``. In the cart-pole kernel it takes two calls' reductions, selects and slow-path checks out of every
substep.

This reaches into another library's private code (libdevice's polynomial and its order of operations), hence the
guard: :func:`verified` compares :func:`sincos` with ``jnp.sin``/``jnp.cos`` bit for bit inside a Pallas kernel on
the GPU at hand (once per process, over 2**16 arguments spread across ``[-LIMIT, LIMIT]`` in bit space, with the
edge cases), and a kernel uses :func:`sincos` only where it returns True; elsewhere it keeps libdevice's calls.
``benchmarks/studies/libdevice_sincos.py`` runs the check over every float in the range (2**31 arguments).

A CPU has neither libdevice nor inline PTX: there the kernels keep ``jnp.sin``/``jnp.cos``, :func:`verified` returns
False, and the tests check :func:`reference` (the same fmas in exact arithmetic) against the true sine and cosine.
"""
from __future__ import annotations

import functools
import math
import warnings
from fractions import Fraction
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

#: The largest ``|t|`` :func:`sincos` serves: ``fl(0.78 * 0.63661975) = 0.4966 < 0.5``, quadrant 0.
LIMIT = 0.78
# libdevice's coefficients (float32 bit patterns, read from libdevice.10.bc of CUDA 13.0;
# verified() checks the GPU's own).
_SIN = ("B94D4153", "3C0885E4", "BE2AAAA8")  # z = (c0 * t2 + c1) * t2 + c2; sin = z * (t2 * t) + t
_COS = ("37CBAC00", "BAB607ED", "3D2AAABB", "BEFFFFFF")  # z = ((c0 * t2 + c1) * t2 + c2) * t2 + c3; cos = z * t2 + 1


def _f32(bits: str) -> np.float32:
    return np.frombuffer(bytes.fromhex(bits)[::-1], np.float32)[0]


def inline_ptx(text: str, *args):
    """One float32 result per element from the PTX ``text`` (``$0`` the result, ``$1``... the float32 ``args``),
    inside a Pallas kernel on a GPU (Triton's elementwise inline assembly; interpret mode has none)."""
    from jax.experimental.pallas import triton as plgpu

    shape = [jax.ShapeDtypeStruct(args[0].shape, jnp.float32)]
    constraints = ",".join(["=r"] + ["r"] * len(args))
    return plgpu.elementwise_inline_asm(text, args=list(args), constraints=constraints, pack=1,
                                        result_shape_dtypes=shape)[0]


def sincos(t):
    """``(sin(t), cos(t))`` as libdevice computes them, for ``|t| <= LIMIT``; inside a Pallas kernel on a GPU only
    (inline PTX). Other arguments get other values: a caller selects libdevice's calls for them."""
    t2 = t * t  # libdevice: mul.rn
    q = inline_ptx("fma.rn.f32 $0, $1, $2, 0f00000000;", t2, t)  # fma(t2, t, 0), the sign of zero as libdevice's
    z = inline_ptx(f"fma.rn.f32 $0, $1, 0f{_SIN[0]}, 0f{_SIN[1]};", t2)
    z = inline_ptx(f"fma.rn.f32 $0, $1, $2, 0f{_SIN[2]};", z, t2)
    sin = inline_ptx("fma.rn.f32 $0, $1, $2, $3;", z, q, t)
    z = inline_ptx(f"fma.rn.f32 $0, $1, 0f{_COS[0]}, 0f{_COS[1]};", t2)
    z = inline_ptx(f"fma.rn.f32 $0, $1, $2, 0f{_COS[2]};", z, t2)
    z = inline_ptx(f"fma.rn.f32 $0, $1, $2, 0f{_COS[3]};", z, t2)
    cos = inline_ptx("fma.rn.f32 $0, $1, $2, 0f3F800000;", z, t2)
    return sin, cos


def _fma(a, b, c) -> np.float32:
    """A float32 fma: the exact ``a * b + c``, rounded once to the nearest float32 (ties to even); an exact zero
    is -0 only where the product and ``c`` are both -0 (IEEE 754, rounding to nearest)."""
    exact = Fraction(float(a)) * Fraction(float(b)) + Fraction(float(c))
    if exact == 0:
        product_sign = math.copysign(1.0, float(a)) * math.copysign(1.0, float(b))
        product_zero = float(a) == 0 or float(b) == 0
        both_negative_zero = product_zero and product_sign < 0 and math.copysign(1.0, float(c)) < 0 and c == 0
        return np.float32(-0.0) if both_negative_zero else np.float32(0.0)
    return _nearest_f32(exact)


def _nearest_f32(x: Fraction) -> np.float32:
    lo = np.float32(float(x))  # within one float32 step of x (float64 rounding, then float32 rounding)
    best = None
    for cand in (np.nextafter(lo, np.float32(-np.inf)), lo, np.nextafter(lo, np.float32(np.inf))):
        err = abs(Fraction(float(cand)) - x)
        if best is None or err < best[0] or (err == best[0] and int(cand.view(np.uint32)) % 2 == 0):
            best = (err, cand)
    return best[1]


def reference(t: float) -> tuple[np.float32, np.float32]:
    """:func:`sincos`'s arithmetic in exact fmas on the host (for tests; slow)."""
    t = np.float32(t)
    t2 = _fma(t, t, np.float32(-0.0))  # t * t (a product's zero is +0 here: t * t >= 0)
    q = _fma(t2, t, np.float32(0.0))
    z = _fma(_fma(t2, _f32(_SIN[0]), _f32(_SIN[1])), t2, _f32(_SIN[2]))
    sin = _fma(z, q, t)
    z = _fma(_fma(_fma(t2, _f32(_COS[0]), _f32(_COS[1])), t2, _f32(_COS[2])), t2, _f32(_COS[3]))
    cos = _fma(z, t2, np.float32(1.0))
    return sin, cos


def sample(n: int = 1 << 16) -> np.ndarray:
    """``n`` float32 arguments spread evenly over the bit patterns of ``[-LIMIT, LIMIT]`` (both signs, zero and the
    subnormals included), and the range's ends."""
    top = int(np.float32(LIMIT).view(np.uint32))
    bits = np.linspace(0, top, n // 2, dtype=np.int64).astype(np.uint32)
    bits = np.concatenate([bits, bits | np.uint32(0x80000000), np.array([top, top - 1, 1, 0x80000001], np.uint32)])
    return bits.view(np.float32)


def mismatches(x) -> jax.Array:
    """How many arguments of ``x`` (float32, a multiple of 128 long) give :func:`sincos` values other than
    ``jnp.sin``/``jnp.cos`` inside a Pallas kernel, bit for bit (GPU only)."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    block = 128

    def kernel(x_ref, o_ref):
        a = x_ref[...]
        s, c = sincos(a)
        bits = lambda v: jax.lax.bitcast_convert_type(v, jnp.int32)  # noqa: E731
        o_ref[...] = ((bits(s) != bits(jnp.sin(a))) | (bits(c) != bits(jnp.cos(a)))).astype(jnp.int32)

    x = jnp.asarray(x, jnp.float32)
    spec = pl.BlockSpec((block,), lambda i: (i,))
    out = pl.pallas_call(kernel, out_shape=jax.ShapeDtypeStruct(x.shape, jnp.int32), grid=(x.shape[0] // block,),
                         in_specs=[spec], out_specs=spec, compiler_params=plgpu.CompilerParams(num_warps=4))(x)
    return jnp.sum(out)


@functools.cache
def verified() -> bool:
    """True where :func:`sincos` gives libdevice's values on this process's GPU (checked once, on :func:`sample`);
    False on other backends or where any argument differs (then the kernels keep libdevice's calls)."""
    if jax.default_backend() != "gpu":
        return False
    x = sample()
    x = np.concatenate([x, np.zeros((-len(x)) % 128, np.float32)])
    try:
        # Run now even when asked while a chunk is being traced (the kernels ask when they are built).
        with jax.ensure_compile_time_eval():
            bad = int(jax.jit(mismatches)(x))
    except Exception as err:  # noqa: BLE001 - a Triton without inline assembly, another lowering: keep libdevice
        warnings.warn(f"jaxrobo.physics.libdevice_sincos: the check did not run ({type(err).__name__}: {err}); "
                      "the kernels keep libdevice's sin/cos calls", RuntimeWarning, stacklevel=2)
        return False
    if bad:
        warnings.warn(f"jaxrobo.physics.libdevice_sincos: {bad} of {len(x)} arguments differ from this GPU's "
                      "libdevice; the kernels keep libdevice's sin/cos calls", RuntimeWarning, stacklevel=2)
    return bad == 0


class WrittenOut(NamedTuple):
    """:func:`sincos` with the range it holds libdevice's values on (``|t| <= limit``)."""

    sincos: Callable
    limit: float


def written_out() -> WrittenOut | None:
    """:func:`sincos` and :data:`LIMIT` where :func:`verified` on this process's GPU, else None (libdevice's calls):
    what a kernel is handed when the plan's ``fast_sincos`` is on."""
    return WrittenOut(sincos, LIMIT) if verified() else None
