"""Registers, occupancy and issue rate of the cart-pole chunk kernel per variant, read by Nsight Compute.

The kernel (:mod:`envs.cartpole.kernel`) is bound by latency: a program is one warp, and the warps an SM
holds at once hide each other's latency. How many it holds is set by the registers a thread uses (65,536 per SM).
For each variant of ``randomisation_cost.py`` this profiles the first launch of the kernel in a short training
(``ncu --kernel-name regex:cartpole --launch-count 1``; the training's later launches still run, slowly, under
ncu: keep ``--nepisodes`` small) and prints its registers per thread, theoretical and
achieved occupancy, issued instructions per cycle and the launch's duration::

    python benchmarks/kernel_occupancy.py --variants kernel-nominal,kernel-physics-only --out occupancy.json

Needs a CUDA GPU and Nsight Compute's ``ncu`` (on PATH or in /usr/local/cuda/bin) with access to the GPU's
performance counters. Registers and occupancy do not depend on the batch size; the issue rate and the duration
do (``--n-envs``), and a first launch includes no compile but is one chunk only.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
#: ncu's metric names, as its details page prints them, and the keys of a row.
METRICS = {"Registers Per Thread": "registers", "Theoretical Occupancy": "theoretical_occupancy_percent",
           "Achieved Occupancy": "achieved_occupancy_percent", "Issued Ipc Active": "issued_ipc",
           "Duration": "duration", "Block Limit Registers": "blocks_per_sm_by_registers"}


def find_ncu() -> str | None:
    """Nsight Compute's command line: on PATH or under /usr/local/cuda/bin."""
    found = shutil.which("ncu")
    if found:
        return found
    path = "/usr/local/cuda/bin/ncu"
    return path if os.access(path, os.X_OK) else None


def parse(text: str) -> dict:
    """The metrics of :data:`METRICS` from ncu's details page (the first value of each), numbers as floats."""
    row = {}
    for line in text.splitlines():
        for name, key in METRICS.items():
            m = re.match(rf"\s+{re.escape(name)}\s+(\S+(?:/\S+)?)?\s+([\d.,]+)\s*$", line)
            if m and key not in row:
                row[key] = float(m.group(2).replace(",", ""))
                if key == "duration":
                    row["duration_unit"] = m.group(1)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="kernel-nominal,kernel-physics-only",
                    help="comma list of randomisation_cost.py's variants (physics-only and randomised are one program)")
    ap.add_argument("--n-envs", type=int, default=262144)
    ap.add_argument("--nepisodes", type=int, default=20,
                    help="episodes per env of the profiled training (its later launches run slowly under ncu)")
    ap.add_argument("--out", default=None, help="JSON of the rows")
    args = ap.parse_args()
    ncu = find_ncu()
    if ncu is None:
        ap.error("no ncu found (PATH, /usr/local/cuda/bin): this needs Nsight Compute")
    rows = []
    for variant in args.variants.split(","):
        cmd = [ncu, "--kernel-name", "regex:cartpole", "--launch-count", "1", "--section", "LaunchStats",
               "--section", "Occupancy", "--section", "ComputeWorkloadAnalysis", "--section", "SpeedOfLight",
               sys.executable, os.path.join(HERE, "randomisation_cost.py"), "--device", "gpu",
               "--envs", "CartPoleStayUp-v0",
               "--n-envs", str(args.n_envs), "--nepisodes", str(args.nepisodes), "--repeats", "1",
               "--variants", variant]
        run = subprocess.run(cmd, capture_output=True, text=True)
        row = {"variant": variant, "n_envs": args.n_envs, **parse(run.stdout)}
        if run.returncode != 0 or "registers" not in row:
            row["error"] = (run.stdout + run.stderr)[-3000:]
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "error"}), flush=True)
        if "error" in row:
            print(row["error"], file=sys.stderr, flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump(rows, f, indent=1)
    return 0 if all("error" not in r for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
