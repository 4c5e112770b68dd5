"""libdevice's sinf/cosf written out for small arguments (:mod:`jaxrobo.physics.libdevice_sincos`). The bit-for-bit
check against libdevice needs a GPU (``benchmarks/studies/libdevice_sincos.py``, and :func:`verified` before a kernel
uses it); here: the coefficients and the order of the fmas make a sine and a cosine (the host's exact-arithmetic
reference within an ulp of the true values), the signs of zero, and the guard's behaviour on every outcome."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.physics import libdevice_sincos as lds


def test_the_written_out_polynomials_are_a_sine_and_a_cosine():
    xs = lds.sample(1 << 11)
    assert np.abs(xs).max() == np.float32(lds.LIMIT) and (xs == 0).any() and (np.abs(xs[xs != 0]) < 1e-38).any()
    worst = 0.0
    for x in xs:
        sin, cos = lds.reference(x)
        for got, true in ((sin, np.sin(np.float64(x))), (cos, np.cos(np.float64(x)))):
            ulp = np.spacing(np.float32(abs(true))) if true != 0 else np.float32(2.0**-149)
            worst = max(worst, abs(float(got) - true) / float(ulp))
    assert worst < 1.0, worst


def test_signed_zeros_and_the_smallest_arguments():
    sin, cos = lds.reference(np.float32(-0.0))
    assert np.signbit(sin) and cos == 1.0
    sin, _ = lds.reference(np.float32(0.0))
    assert not np.signbit(sin)
    tiny = np.float32(-1e-45)
    assert lds.reference(tiny) == (tiny, np.float32(1.0))


def test_the_guard_is_off_on_a_cpu():
    assert jax.default_backend() != "gpu" and lds.verified() is False


@pytest.mark.parametrize("outcome", ["equal", "differs", "fails"])
def test_the_guard_checks_even_while_a_chunk_is_traced(outcome, monkeypatch):
    """The kernels ask while their chunk is traced: the check still runs on concrete values. A difference or a
    check that cannot run turns the written-out form off, with a warning saying which."""
    def mismatches(x):
        if outcome == "fails":
            raise NotImplementedError("no inline assembly here")
        return jnp.sum(jnp.asarray(x) == np.float32(lds.LIMIT)).astype(jnp.int32) * (outcome == "differs")

    monkeypatch.setattr(lds, "mismatches", mismatches)
    monkeypatch.setattr(lds.jax, "default_backend", lambda: "gpu")
    seen = []

    @jax.jit
    def chunk(y):
        seen.append(lds.verified.__wrapped__())
        return y

    if outcome == "equal":
        chunk(1.0)
    else:
        with pytest.warns(RuntimeWarning, match="keep libdevice's sin/cos calls"):
            chunk(1.0)
    assert seen == [outcome == "equal"]
