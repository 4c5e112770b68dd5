"""The values a tree's cart-pole kernel gives on this device: a randomised (noisy) training's tables and records
hashed, and, where the tree has the kernel-local ``_erf_inv``, its bits against ``jax.lax.erf_inv``'s inside a
Pallas kernel on every float32 in [nextafter(-1, 0), 1) at a stride. Run from a tree's root: prints one JSON line."""
import hashlib
import json
import os
import sys

sys.path.insert(0, os.getcwd())
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxrobo.speed import fused_pallas  # noqa: E402
from jaxrobo.training.run import resolve  # noqa: E402
from jaxrobo.training.train import train  # noqa: E402

out = {"device": jax.devices()[0].device_kind}
ranges = {"rand_cart_mass": [0.8, 1.2], "rand_pole_mass": [0.8, 1.2], "rand_pole_length": [0.9, 1.1],
          "rand_obs_noise": [0.0, 0.01]}
spec = resolve("CartPoleStayUp-v0", "default", {"backend": "analytic", "randomise": True, **ranges,
                                                "n_envs": 4096, "nepisodes": 20, "eval_episodes": 0})
r = train(spec.env, spec.config, spec.agent_params)
digest = hashlib.sha256()
for a in (r.q, r.returns, r.lengths):
    digest.update(np.ascontiguousarray(a).tobytes())
out.update(plan=r.plan, env_steps=int(r.env_steps), tables_and_records_sha256=digest.hexdigest())

if hasattr(fused_pallas, "_erf_inv"):
    from jax.experimental import pallas as pl

    lo = np.nextafter(np.float32(-1), np.float32(0))
    x = np.concatenate([np.linspace(lo, 1, 2_000_000, endpoint=False, dtype=np.float32),
                        np.float32([lo, -0.5, 0.0, 0.5, np.nextafter(np.float32(1), np.float32(0))]),
                        np.float32([0.99999994, -0.99999994, 1e-30])])
    x = np.pad(x, (0, (-len(x)) % 1024))

    def kern(f):
        def k(x_ref, o_ref):
            o_ref[...] = f(x_ref[...])
        return k

    def run(f):
        call = pl.pallas_call(kern(f), out_shape=jax.ShapeDtypeStruct(x.shape, jnp.float32), grid=(len(x) // 1024,),
                              in_specs=[pl.BlockSpec((1024,), lambda i: (i,))],
                              out_specs=pl.BlockSpec((1024,), lambda i: (i,)), interpret=jax.default_backend() == "cpu")
        return np.asarray(jax.jit(call)(jnp.asarray(x)))

    a, b = run(jax.lax.erf_inv), run(fused_pallas._erf_inv)
    same = (a.view(np.int32) == b.view(np.int32)) | (np.isnan(a) & np.isnan(b))
    out.update(erfinv_values=int(len(x)), erfinv_bits_equal=int(same.sum()),
               erfinv_max_abs_diff=float(np.nanmax(np.abs(a.astype(np.float64) - b))))
print(json.dumps(out), flush=True)
