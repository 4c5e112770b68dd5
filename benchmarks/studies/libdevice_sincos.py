"""Check :func:`jaxrobo.physics.libdevice_sincos.sincos` against libdevice's ``sinf``/``cosf`` on this GPU over every
float32 in ``[-LIMIT, LIMIT]`` (2**31 arguments, both signs, zero and the subnormals), bit for bit, inside Pallas
kernels; and the host's exact-arithmetic :func:`~jaxrobo.physics.libdevice_sincos.reference` against the GPU's values on
a sample. The kernels check the same on a sample once per process (:func:`~jaxrobo.physics.libdevice_sincos.verified`)
before they use it.

    python benchmarks/studies/libdevice_sincos.py --out benchmarks/results/h100/libdevice_sincos.json
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: _common
import _common  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help="write the result as JSON here")
    p.add_argument("--reference", type=int, default=4096, help="arguments for the host reference's check")
    args = p.parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxrobo.physics import libdevice_sincos as lds

    if jax.default_backend() != "gpu":
        print("needs a GPU (libdevice and inline PTX): nothing to check here")
        return 2
    top = int(np.float32(lds.LIMIT).view(np.uint32))
    chunk = 1 << 26

    @jax.jit
    def count(start):
        bits = start + jax.lax.iota(jnp.uint32, chunk)
        inside = (bits & jnp.uint32(0x7FFFFFFF)) <= top
        x = jnp.where(inside, jax.lax.bitcast_convert_type(bits, jnp.float32), 0.0)
        return lds.mismatches(x)

    t0 = time.perf_counter()
    bad = 0
    for sign in (0, 0x80000000):
        for start in range(0, top + 1, chunk):
            bad += int(count(jnp.uint32(sign + start)))
    seconds = time.perf_counter() - t0

    # The host's reference against the GPU's values (the kernel's own, through sincos in a Pallas kernel).
    from jax.experimental import pallas as pl

    xs = lds.sample(args.reference)
    xs = np.concatenate([xs, np.zeros((-len(xs)) % 128, np.float32)])

    def kernel(x_ref, s_ref, c_ref):
        s_ref[...], c_ref[...] = lds.sincos(x_ref[...])

    spec = pl.BlockSpec((128,), lambda i: (i,))
    shape = jax.ShapeDtypeStruct(xs.shape, jnp.float32)
    s, c = pl.pallas_call(kernel, out_shape=(shape, shape), grid=(len(xs) // 128,), in_specs=[spec],
                          out_specs=(spec, spec))(jnp.asarray(xs))
    ref = np.array([lds.reference(x) for x in xs], np.float32)
    host_bad = int(np.sum((np.asarray(s).view(np.int32) != ref[:, 0].view(np.int32))
                          | (np.asarray(c).view(np.int32) != ref[:, 1].view(np.int32))))
    row = {"device": f"{jax.devices()[0].device_kind}, jax {jax.__version__}", "limit": lds.LIMIT,
           "arguments": 2 * (top + 1), "mismatches": bad, "seconds": seconds, "verified": lds.verified(),
           "reference_arguments": len(xs), "reference_mismatches": host_bad}
    print(f"sincos vs libdevice over all {row['arguments']:,} float32 in [-{lds.LIMIT}, {lds.LIMIT}]: {bad} "
          f"mismatches ({seconds:.1f} s); verified() {row['verified']}; host reference vs GPU on {len(xs)}: "
          f"{host_bad} mismatches")
    if args.out:
        _common.write_json(row, args.out)
    return 0 if bad == 0 and host_bad == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
