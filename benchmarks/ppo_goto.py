"""PPO (Brax's trainer, unchanged) on the continuous Goto: arrivals on 200 fresh goals with the obstacle, median of
3 seeds, and the wall time to reach the target on one device.

    python benchmarks/ppo_goto.py --device gpu   # the preset of agents/configs/ppo/QuadcopterGotoTwist-v0.yaml
    python benchmarks/ppo_goto.py --device cpu --preset tiny --seeds 0 --eval-episodes 8    # a smoke run

Each seed is one ``jaxrobo train --env QuadcopterGotoTwist-v0 --agent ppo`` run (:func:`jaxrobo.deep.train`): the
deterministic policy is evaluated on ``--eval-episodes`` fresh random goals (obstacle between start and goal) at
each of the preset's ``num_evals`` points. Per seed: the final arrival rate, and the first evaluation point at
which it reaches ``--target``: its env steps and its wall time (training wall time from the start of the trainer
call, compile included, the evaluations themselves excluded). Summary: the median over seeds of the final arrival
rate and of the time to the target (a seed that never reaches it counts as never; the median then is too when it
is most of them). Written to ``benchmarks/results/<device>/ppo_goto.json``.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common  # noqa: E402

ENV_ID = "QuadcopterGotoTwist-v0"
#: L2F (learning to fly) trains a quadrotor policy in 18 s on a laptop GPU: the reference point of the report.
L2F_SECONDS = 18.0


def first_reaching(evaluations: list[dict], target: float) -> dict | None:
    """The first evaluation whose arrival rate is >= ``target`` (None if none)."""
    import numpy as np

    for e in evaluations:
        if float(np.mean(e["success"])) >= target:
            return e
    return None


def median_or_none(values: list[float | None]) -> float | None:
    """The median, a None (never reached) counting as +infinity; None when the median itself is infinite."""
    import numpy as np

    x = np.sort(np.asarray([np.inf if v is None else v for v in values], np.float64))
    m = float(np.median(x))
    return None if not np.isfinite(m) else m


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", choices=("cpu", "gpu"), default=None)
    parser.add_argument("--preset", default="default")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    parser.add_argument("--eval-episodes", type=int, default=200, help="fresh goals per evaluation")
    parser.add_argument("--target", type=float, default=0.95, help="arrival rate to reach")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override (repeatable)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    _common.select_device(args.device)
    import numpy as np

    from jaxrobo import deep
    from jaxrobo.core.config import parse_overrides

    try:
        from jaxrobo.speed.cache import enable_compilation_cache

        enable_compilation_cache()  # seeds after the first reuse the first one's executables
    except ImportError:
        pass
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    overrides = parse_overrides(args.set)
    runs: list[dict] = []
    for seed in seeds:
        spec = deep.resolve(ENV_ID, "ppo", args.preset, {**overrides, "seed": seed,
                                                          "eval_episodes": args.eval_episodes})
        t0 = time.perf_counter()
        result = deep.train(spec, lambda point: print(
            f"  seed {seed}: {point.row['env_steps']:>11,} steps {point.row['seconds']:6.1f} s  arrivals "
            f"{np.mean(point.row['success']):.3f}  return {np.mean(point.row['return']):7.1f}", flush=True))
        wall = time.perf_counter() - t0
        hit = first_reaching(result.evaluations, args.target)
        final = float(np.mean(result.evaluations[-1]["success"]))
        runs.append({"seed": seed, "final_arrival_rate": final,
                     "best_arrival_rate": max(float(np.mean(e["success"])) for e in result.evaluations),
                     "arrival_rate_curve": [[int(e["env_steps"]), round(float(e["seconds"]), 3),
                                             float(np.mean(e["success"]))] for e in result.evaluations],
                     "seconds_to_target": None if hit is None else round(float(hit["seconds"]), 3),
                     "env_steps_to_target": None if hit is None else int(hit["env_steps"]),
                     "train_seconds": round(result.seconds - result.eval_seconds, 3), "wall_seconds": round(wall, 3),
                     "env_steps": result.env_steps})
        print(f"seed {seed}: final arrivals {final:.3f}; target {args.target} "
              + (f"reached at {hit['env_steps']:,} steps, {hit['seconds']:.1f} s" if hit else "not reached"),
              flush=True)
        # the JSON so far after each seed, so that a run cut short keeps the seeds it finished
        _common.write_json(summarize(args, overrides, seeds[:len(runs)], runs, argv), args.out, "ppo_goto.json")
    out = summarize(args, overrides, seeds, runs, argv)
    path = _common.write_json(out, args.out, "ppo_goto.json")
    to_target = out["median_seconds_to_target"]
    print(f"median final arrival rate {out['median_final_arrival_rate']:.3f} over seeds {seeds} "
          f"(min {out['min_final_arrival_rate']:.3f}, max {out['max_final_arrival_rate']:.3f}); median time to "
          f"{args.target}: " + (f"{to_target:.1f} s ({out['times_l2f']}x L2F's {L2F_SECONDS:.0f} s)"
                                if to_target is not None else "not reached"))
    print(path)
    return 0


def summarize(args, overrides: dict, seeds: list[int], runs: list[dict], argv) -> dict:
    import numpy as np

    from jaxrobo import deep

    finals = [r["final_arrival_rate"] for r in runs]
    to_target = median_or_none([r["seconds_to_target"] for r in runs])
    out = {
        "benchmark": "ppo_goto", "env_id": ENV_ID, "preset": args.preset, "overrides": overrides,
        "config": deep.resolve(ENV_ID, "ppo", args.preset, {**overrides, "eval_episodes": args.eval_episodes})
        .to_dict()["train"],
        "device": _common.device_name(), "platform": platform.platform(), "eval_episodes": args.eval_episodes,
        "target": args.target, "seeds": seeds, "runs": runs,
        "median_final_arrival_rate": float(np.median(finals)),
        "min_final_arrival_rate": float(min(finals)), "max_final_arrival_rate": float(max(finals)),
        "median_seconds_to_target": to_target,
        "l2f_seconds": L2F_SECONDS,
        "times_l2f": None if to_target is None else round(to_target / L2F_SECONDS, 2),
        "command": "python benchmarks/ppo_goto.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    return out


if __name__ == "__main__":
    sys.exit(main())
