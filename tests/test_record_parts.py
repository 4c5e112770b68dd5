"""The records' parts computed on the device (:mod:`jaxrobo.training.record_parts`) give the summary's figures and
``episode_stats.csv`` bit for bit as the records do on the host: records with unrecorded slots, envs with none,
fewer and more than 100 episodes, NaN returns, signed zeros and ties, both ranking directions, both figures."""
from __future__ import annotations

import json
import os
import warnings

import jax
import numpy as np
import pytest

from jaxrobo.io import results
from jaxrobo.task.env import LearningTarget, ranking
from jaxrobo.training import record_parts
from jaxrobo.training.summary import TrainResult, _figures_from_parts
from jaxrobo.training.trainer import TrainConfig

#: (envs, slots, recorded per env: "mixed" | "all", learning target or None, NaN returns among the recorded)
CASES = {
    "masked, length window": (300, 150, "mixed", None, False),
    "NaN returns": (300, 150, "mixed", None, True),
    "fewer slots than 100": (60, 40, "mixed", None, True),
    "all recorded": (40, 130, "all", None, False),
    "shorter is better": (200, 140, "mixed", LearningTarget("quick", "mean_length", 50.0, "short", better="lower"),
                          False),
    "ranked by return": (200, 140, "mixed", LearningTarget("earns", "mean_return", 10.0, "a return of 10"), False),
}


def _records(n: int, slots: int, recorded: str, nan: bool = False, seed: int = 3):
    rng = np.random.default_rng(seed)
    if recorded == "all":
        done = np.full(n, slots + 7)  # past the slots: all recorded
    else:
        done = rng.integers(0, slots + 1, n)
        done[: n // 3] = rng.integers(100, slots + 1, n // 3) if slots >= 100 else slots
        done[0], done[1] = 0, slots
    lengths = rng.integers(1, 40, (n, slots)).astype(np.int32)  # few values: ties in every sort
    returns = (lengths * rng.standard_normal((n, slots)) * 0.5).round(1).astype(np.float32)
    returns[rng.random((n, slots)) < 0.02] = -0.0
    if nan:
        returns[rng.random((n, slots)) < 0.005] = np.nan
    unwritten = np.arange(slots)[None, :] >= done[:, None]
    returns[unwritten], lengths[unwritten] = 0, 0  # as a run leaves them
    return returns, lengths, done.astype(np.int32)


@pytest.mark.parametrize("case", list(CASES))
def test_the_parts_give_the_figures_and_statistics_of_the_records(case):
    n, slots, recorded, target, nan = CASES[case]
    returns, lengths, episode = _records(n, slots, recorded, nan)
    rank = ranking(target)
    parts = jax.device_get(jax.jit(record_parts.parts, static_argnames="higher")(
        returns, lengths, episode, higher=rank.higher))
    all_recorded = recorded == "all"
    done = np.minimum(episode, slots)
    result = TrainResult(env_id="test", config=TrainConfig(n_envs=n, nepisodes=slots), agent_params=None,
                         returns=returns, lengths=lengths, terminated=lengths > 20, epsilon=np.linspace(1, 0, slots),
                         nan_episodes=np.zeros(n, np.int32), env_steps=int(lengths.sum()), q=np.zeros(1),
                         compile_seconds=0.0, run_seconds=1.0, episodes_done=done, learning_target=target)
    host = result._figures(rank)
    device = _figures_from_parts(parts, returns, done, all_recorded, rank)
    assert host.keys() == device.keys()
    for name in host:
        assert np.array_equal(host[name], device[name], equal_nan=True), (name, host[name], device[name])
    assert nan or not any(np.isnan(v) for v in host.values())

    if not all_recorded:  # the percentiles' parts serve a run whose envs recorded different counts
        order = {"returns": parts["order_returns"], "lengths": parts["order_lengths"]}
        here = results.episode_stats(returns, lengths, result.epsilon, done)
        there = results.episode_stats(returns, lengths, result.epsilon, done, order_stats=order)
        for name, x, y in zip(results.STAT_COLUMNS, here, there):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name
        # ... and they are numpy's own figures over the recorded entries
        masked = np.where(np.arange(slots)[None, :] < done[:, None], returns.astype(np.float64), np.nan)
        n_ep = int(done.max())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a column of NaN returns only: its mean is NaN
            np.testing.assert_array_equal(there[1], np.nanmean(masked, 0)[:n_ep])
            np.testing.assert_array_equal(there[2], np.nanstd(masked, 0)[:n_ep])
            if nan:  # a NaN return counts among a column's entries for its ranks (sorted last), as it always has
                return
            # (numpy's interpolation rounds in another order: the same up to the last bit)
            np.testing.assert_allclose(there[3:6], np.nanpercentile(masked, [10, 50, 90], axis=0)[:, :n_ep],
                                       rtol=1e-14, atol=1e-14)


def test_the_device_ranks_are_numpys():
    """:func:`record_parts.column_ranks` (whole numbers, on the device) and ``percentile_ranks`` (numpy's float64
    positions, floored) agree for every count up to a million."""
    count = np.arange(0, 1_000_001)
    device = np.asarray(jax.jit(record_parts.column_ranks)(count.astype(np.int32)))
    host = results.percentile_ranks(np.maximum(count, 1))[1]
    np.testing.assert_array_equal(device, host)


def test_order_statistics_of_the_wrong_shape_are_refused():
    returns, lengths, episode = _records(30, 20, "mixed")
    with pytest.raises(ValueError, match=r"order_stats\['returns'\]: expected 6 rows"):
        results.episode_stats(returns, lengths, np.zeros(20), episode,
                              order_stats={"returns": np.zeros((3, 20)), "lengths": np.zeros((6, 20))})


def test_a_run_computes_its_parts_on_the_device_where_wanted(monkeypatch, tmp_path):
    """End to end through the driver: a run made to take its parts from the device (as a large one on a GPU does)
    writes the summary's figures and ``episode_stats.csv`` the records give; on a CPU device no run does."""
    from jaxrobo.io.results import save_run
    from jaxrobo.training.run import resolve
    from jaxrobo.training.train import train
    from jaxrobo.training.trainer import Trainer

    assert not record_parts.wanted(1 << 20, 330, 500, backend="cpu")
    assert record_parts.wanted(1 << 20, 330, 500, backend="gpu") == (jax.process_count() == 1)
    assert not record_parts.wanted(1 << 10, 330, 500, backend="gpu")  # small: the host is as quick
    assert not record_parts.wanted(1 << 20, 330, 1 << 23, backend="gpu")  # an env's length sum past int32

    monkeypatch.setattr(record_parts, "wanted", lambda *a, **k: True)
    spec = resolve("CartPoleStayUp-v0", overrides=dict(n_envs=24, nepisodes=140, nsteps=30, chunk_steps=40,
                                                         total_steps=24 * 2200, eval_episodes=2, eval_envs=2,
                                                         stop_at_target=False))
    result = train(spec.env, spec.config, spec.agent_params)
    assert result.record_parts is not None and not result.all_recorded()
    assert int(result.episodes_done.max()) >= 100  # the windows of 100 episodes are used
    from dataclasses import replace

    written = {}
    for name, r in (("device", result), ("host", replace(result, record_parts=None))):
        out = str(tmp_path / name)
        save_run(out, r, spec.to_dict(), Trainer(spec.env, spec.config).disc)
        with open(os.path.join(out, "summary.json")) as f:
            summary = json.load(f)
        with open(os.path.join(out, "episode_stats.csv")) as f:
            written[name] = (summary, f.read())
    (summary_d, stats_d), (summary_h, stats_h) = written["device"], written["host"]
    assert stats_d == stats_h
    assert summary_d == summary_h


def test_parts_that_fail_leave_the_figures_to_the_host(monkeypatch):
    """A device that cannot compute the parts (out of memory, say) costs the run nothing but time: a warning, and
    the host computes the figures and statistics from the records."""
    def failing(higher):
        def program(*args):
            raise RuntimeError("RESOURCE_EXHAUSTED: out of memory")
        return program

    monkeypatch.setattr(record_parts, "_program", failing)
    returns, lengths, episode = _records(8, 5, "mixed")
    prepared = record_parts.Prepared(returns, lengths, episode, higher=True)
    with pytest.warns(RuntimeWarning, match="RESOURCE_EXHAUSTED.*the host computes"):
        assert prepared.start(returns, lengths, episode).result() is None


#: A run split over 4 (CPU) devices with the parts forced on: the records are sharded over the envs, and the
#: program's sorts over each column gather them; the figures equal the host's.
SPLIT = r"""
import json, sys, warnings
sys.path.insert(0, sys.argv[1])
import jax
from jaxrobo.training import record_parts
from jaxrobo.training.run import resolve
from jaxrobo.training.train import train

record_parts.wanted = lambda *a, **k: True
spec = resolve("CartPoleStayUp-v0", overrides=dict(n_envs=16, nepisodes=130, nsteps=30, chunk_steps=40,
               total_steps=16 * 2200, eval_episodes=2, eval_envs=2, stop_at_target=False, devices=4))
with warnings.catch_warnings():
    warnings.simplefilter("error", RuntimeWarning)  # the parts' fallback warns: here it must not be taken
    result = train(spec.env, spec.config, spec.agent_params)
device = result.summary()
result.record_parts = None
host = result.summary()
keys = [k for k in host if "second" not in k]
print("RESULT" + json.dumps({"devices": jax.device_count(), "plan": result.plan,
                             "same": all(device[k] == host[k] for k in keys)}))
"""


@pytest.mark.slow
def test_a_run_split_over_devices_takes_the_same_parts():
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXROBO_CACHE_DIR": "off",
           "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
    proc = subprocess.run([sys.executable, "-c", SPLIT, root], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.split("RESULT", 1)[1])
    assert out["devices"] == 4 and "devices=4" in out["plan"] and out["same"], out
