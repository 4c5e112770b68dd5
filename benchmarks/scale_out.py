"""``jaxrobo train`` and ``jaxrobo sweep`` on 1, 2, ... GPUs of one host, end to end, with checksums.

    python benchmarks/scale_out.py --gpus 1,2,4 --kind train --env CartPoleStayUp-v0 --set env.backend=analytic \
        --n-envs 1048576 --total-steps 2000000000000 --out rows.json
    python benchmarks/scale_out.py --gpus 1,2,4 --kind sweep --env QuadcopterGoto-v2 --n-envs 64 --seeds 4096 \
        --total-steps 4000000 --out rows.json
    python benchmarks/scale_out.py --gpus 1,2,4,4p --kind sweep ...   # 4p: 4 processes, one GPU each
    python benchmarks/scale_out.py --gpus 2 --distributed ...            # every entry as one process per GPU

Each run is the user's command in fresh processes with ``CUDA_VISIBLE_DEVICES`` naming its GPUs (an entry ``Np``,
or every entry under ``--distributed``: one process per GPU joined by ``jax.distributed``,
``JAXROBO_COORDINATOR`` on localhost, process 0 writing). A row gives the wall time from start to exit, the
summary's compile and run seconds, useful env steps per second of the run and of the wall, the speed-up and
efficiency (speed-up x baseline GPUs / GPUs) of the run and of the wall over the first ``--gpus`` entry, and a
checksum of what the run wrote (``qtables.npz`` and ``records.npz`` for train, ``sweep.csv`` for a sweep), which
must be the same on every count of GPUs and processes. A table of them ends the output; ``--out`` writes the rows
as JSON.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402


def checksum(kind: str, out: str) -> str:
    h = hashlib.sha256()
    if kind == "sweep":
        with open(os.path.join(out, "sweep.csv"), "rb") as f:
            h.update(f.read())
        return h.hexdigest()[:16]
    for name, keys in (("qtables.npz", ("q",)), ("records.npz", ("returns", "lengths", "terminated"))):
        with np.load(os.path.join(out, name), allow_pickle=False) as data:
            for k in keys:
                a = np.ascontiguousarray(data[k])
                h.update(str((a.shape, a.dtype.str)).encode() + a.tobytes())
    return h.hexdigest()[:16]


def command(args, out: str) -> list[str]:
    sets = [x for s in args.set for x in ("--set", s)]
    if args.kind == "train":
        return ["train", "--env", args.env, "--n-envs", str(args.n_envs), "--total-steps", str(args.total_steps),
                "--nepisodes", str(args.nepisodes), "--no-progress", "--out", out, *sets]
    return ["sweep", "--env", args.env, "--grid", args.grid, "--seeds", str(args.seeds), "--n-envs",
            str(args.n_envs), "--total-steps", str(args.total_steps), "--nepisodes", str(args.nepisodes),
            "--no-plots", "--no-progress", "--eval-episodes", str(args.eval_episodes), "--out", out, *sets]


def parse_counts(text: str, distributed: bool) -> list[tuple[int, bool]]:
    """``"1,2,4,4p"`` → ``[(1, False), (2, False), (4, False), (4, True)]`` (``p``: one process per GPU)."""
    out = []
    for item in text.split(","):
        item = item.strip()
        many = item.endswith("p")
        try:
            n = int(item[:-1] if many else item)
        except ValueError:
            raise SystemExit(f"--gpus {text!r}: expected a comma list of counts, each optionally ending in p") from None
        if n < 1:
            raise SystemExit(f"--gpus {text!r}: counts must be >= 1")
        out.append((n, many or distributed))
    return out


def run_one(args, gpus: int, tmp: str, distributed: bool = False) -> dict:
    out = os.path.join(tmp, f"run{gpus}{'p' if distributed else ''}")
    argv = [sys.executable, "-m", "jaxrobo.cli", *command(args, out)]
    base = dict(os.environ)
    t0 = time.perf_counter()
    if distributed and gpus > 1:
        port = _common.free_port()
        procs = [subprocess.Popen(argv, env={**base, "CUDA_VISIBLE_DEVICES": str(i),
                                             "JAXROBO_COORDINATOR": f"localhost:{port}",
                                             "JAXROBO_NUM_PROCESSES": str(gpus), "JAXROBO_PROCESS_ID": str(i)},
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(gpus)]
        outs = [p.communicate() for p in procs]
        rcs = [p.returncode for p in procs]
        text = outs[0][0] + outs[0][1]
    else:
        p = subprocess.run(argv, env={**base, "CUDA_VISIBLE_DEVICES": ",".join(map(str, range(gpus)))},
                           capture_output=True, text=True)
        rcs, text = [p.returncode], p.stdout + p.stderr
    wall = time.perf_counter() - t0
    if any(rcs):
        return {"gpus": gpus, "processes": gpus if distributed else 1, "status": "failed", "returncodes": rcs,
                "output": text[-3000:]}
    with open(os.path.join(out, "summary.json")) as f:
        s = json.load(f)
    run_s = s.get("run_seconds") or sum(g["run_seconds"] for g in s.get("groups", []))
    compile_s = s.get("compile_seconds") or sum(g["compile_seconds"] for g in s.get("groups", []))
    return {"gpus": gpus, "processes": gpus if distributed else 1, "status": "ok", "wall_s": wall,
            "compile_s": compile_s, "run_s": run_s, "eval_s": s.get("eval_seconds"),
            "write_s": s.get("write_seconds"), "env_steps": s["env_steps"],
            "useful_share": s.get("useful_share"), "steps_per_s_run": s["env_steps"] / max(run_s, 1e-9),
            "steps_per_s_wall": s["env_steps"] / wall, "checksum": checksum(args.kind, out),
            "plan": s.get("execution_plan"), "tail": text[-600:]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gpus", default="1,2,4", help="comma list of GPU counts, Np for N processes of one GPU each "
                                                   "(the first is the baseline)")
    p.add_argument("--kind", choices=("train", "sweep"), default="train")
    p.add_argument("--env", default="CartPoleStayUp-v0")
    p.add_argument("--n-envs", type=int, default=1 << 20, help="train: envs; sweep: envs per row")
    p.add_argument("--seeds", type=int, default=256, help="sweep: seeds per configuration")
    p.add_argument("--grid", default="alpha=0.1,0.2,0.3,0.5", help="sweep: the --grid")
    p.add_argument("--total-steps", type=int, required=True, help="the step budget (train: the run's; sweep: a row's)")
    p.add_argument("--nepisodes", type=int, default=20, help="episodes each env records")
    p.add_argument("--eval-episodes", type=int, default=10, help="sweep: greedy episodes per row")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--distributed", action="store_true", help="every entry as one process per GPU (jax.distributed)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    counts = parse_counts(args.gpus, args.distributed)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for g, many in counts:
            row = run_one(args, g, tmp, many)
            rows.append(row)
            base = rows[0]
            if row["status"] == "ok" and base["status"] == "ok":
                row["speedup_run"] = row["steps_per_s_run"] / base["steps_per_s_run"]
                row["speedup_wall"] = row["steps_per_s_wall"] / base["steps_per_s_wall"]
                row["efficiency_run"] = row["speedup_run"] * base["gpus"] / g
                row["efficiency_wall"] = row["speedup_wall"] * base["gpus"] / g
                row["same_as_baseline"] = row["checksum"] == base["checksum"]
            print(json.dumps({k: v for k, v in row.items() if k != "tail"}), flush=True)
    print(f"\n{'gpus':>4s} {'procs':>5s} {'checksum':>16s} {'same':>5s} {'compile_s':>9s} {'run_s':>8s} {'wall_s':>8s} "
          f"{'eff_run':>7s} {'eff_wall':>8s}")
    for r in rows:
        if r["status"] != "ok":
            print(f"{r['gpus']:4d} {r['processes']:5d} failed (exit {r['returncodes']})")
            continue
        print(f"{r['gpus']:4d} {r['processes']:5d} {r['checksum']:>16s} {str(r.get('same_as_baseline', '-')):>5s} "
              f"{r['compile_s']:9.1f} {r['run_s']:8.1f} {r['wall_s']:8.1f} "
              f"{r.get('efficiency_run', float('nan')):7.2f} {r.get('efficiency_wall', float('nan')):8.2f}")
    if args.out:
        _common.write_json({"argv": sys.argv, "kind": args.kind, "distributed": args.distributed, "rows": rows},
                           args.out)
    return 0 if all(r["status"] == "ok" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
