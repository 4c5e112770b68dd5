"""Fingerprints of short training runs: every shipped preset and every learner, on CPU, for fixed seeds.

A refactor of the trainer, the envs or the learners must leave training values bit for bit unchanged; this
records a SHA-256 of each run's Q-tables, episode records and greedy evaluation, so a change shows up as a
different hash. ``tests/test_fingerprints.py`` checks a fast subset on every test run; the whole list is checked
by hand after a change to the core::

    python scripts/fingerprints.py --check tests/data/fingerprints.json          # every case (minutes on 2 cores)
    python scripts/fingerprints.py --write tests/data/fingerprints.json          # record anew (on purpose only)

Values depend on the device and the XLA version: the recorded file is for CPU JAX.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

#: Overrides that make every case a few seconds of training on 2 cores (shapes fixed, so the hash is stable).
SMALL = dict(n_envs=4, nepisodes=6, nsteps=40, chunk_steps=25, eval_episodes=3, eval_envs=2)


def cases() -> list[dict]:
    """(env id, preset, learner, extra overrides) of every case: each id's presets with their own learner, and
    every learner on both cart-pole backends."""
    out = []
    for env_id in ("CartPoleStayUp-v0", "CartPoleStayUpLeftRight-v0", "QuadcopterLiveShow-v0", "QuadcopterGoto-v1"):
        for preset in ("default", "seed"):
            out.append(dict(env_id=env_id, preset=preset, agent=None, extra={}))
    for env_id in ("QuadcopterGoto-v2", "ArmReach-v0"):  # their one preset
        out.append(dict(env_id=env_id, preset="default", agent=None, extra={}))
    for backend in ("analytic", "mjx"):
        for agent in ("qlearn", "sarsa", "expected_sarsa", "double_q"):
            out.append(dict(env_id="CartPoleStayUp-v0", preset="default", agent=agent,
                            extra={"env.backend": backend}))
    return out


def name(case: dict) -> str:
    extra = ",".join(f"{k}={v}" for k, v in sorted(case["extra"].items()))
    return f"{case['env_id']}/{case['preset']}/{case['agent'] or 'preset-agent'}" + (f"/{extra}" if extra else "")


def fingerprint(case: dict) -> str:
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train

    spec = resolve(case["env_id"], case["preset"], {**SMALL, **case["extra"]}, agent=case["agent"])
    r = train(spec.env, spec.config, spec.agent_params)
    h = hashlib.sha256()
    for arr in (r.q, r.returns, r.lengths, r.terminated, r.nan_episodes, np.int64(r.env_steps),
                r.eval_returns, r.eval_lengths):
        a = np.ascontiguousarray(np.asarray(arr))
        h.update(str((a.shape, a.dtype.str)).encode() + a.tobytes())
    return h.hexdigest()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", metavar="JSON", help="record every case's fingerprint to JSON")
    g.add_argument("--check", metavar="JSON", help="compare every case with JSON; exit 1 on a difference")
    p.add_argument("-k", default="", help="only cases whose name contains this text")
    args = p.parse_args(argv)
    from jaxrobo.speed.cache import enable_compilation_cache

    enable_compilation_cache()
    todo = [c for c in cases() if args.k in name(c)]
    if args.write:
        got = {name(c): fingerprint(c) for c in todo}
        with open(args.write, "w") as f:
            json.dump(got, f, indent=1, sort_keys=True)
            f.write("\n")
        print(f"{len(got)} fingerprints -> {args.write}")
        return 0
    with open(args.check) as f:
        want = json.load(f)
    bad = 0
    for c in todo:
        n = name(c)
        got = fingerprint(c)
        ok = want.get(n) == got
        bad += not ok
        print(f"{'ok  ' if ok else 'DIFF'} {n}", flush=True)
    print(f"{len(todo) - bad} same, {bad} different")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
