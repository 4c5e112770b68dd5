"""Training until learned: the learning-target stop (tabular and Brax's trainers) and defaults sized to the device."""
from __future__ import annotations

import numpy as np
import pytest

from jaxrobo.core.config import ConfigError
from jaxrobo.training import run as run_mod
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer

#: The closed-form cart-pole learns within a few thousand steps per env at 64 envs; small flights keep it quick.
from jaxrobo.training.train import train
FAST = {"env.backend": "analytic", "n_envs": 64, "chunk_steps": 250, "eval_episodes": 20, "eval_envs": 2}


@pytest.fixture(scope="module")
def stopped():
    spec = resolve("CartPoleStayUp-v0", overrides={**FAST, "target_every": 2})
    return spec, train(spec.env, spec.config, spec.agent_params)


def test_a_run_stops_once_its_target_holds_on_fresh_episodes(stopped):
    spec, r = stopped
    t = Trainer(spec.env, spec.config)
    assert t.target_every() == 2
    assert r.complete and r.target_met_chunk is not None and r.chunks_done == r.target_met_chunk
    assert r.chunks_done < t.max_chunks()  # before the budget's cap
    assert [c["chunks"] for c in r.target_checks] == list(range(2, r.chunks_done + 1, 2))
    last = r.target_checks[-1]
    assert last["score"] >= 500 and last["confirmed"] >= 500  # met, then met again on other episodes
    assert all(not (c["confirmed"] >= 500) for c in r.target_checks[:-1])  # earlier checks did not hold
    s = r.summary()
    assert s["target_met_in_training"] and s["target_met_at_chunk"] == r.chunks_done
    assert s["target_met_at_env_steps"] == r.env_steps
    # the final evaluation flies other episodes than the checks: the run is judged on those
    assert s["selected_table_fresh_mean_length"] >= 500


def test_a_run_whose_target_never_holds_runs_its_whole_budget():
    spec = resolve("CartPoleStayUp-v0", overrides={**FAST, "n_envs": 2, "nepisodes": 3, "nsteps": 20,
                                                     "chunk_steps": 10, "target_every": 1})
    r = train(spec.env, spec.config, spec.agent_params)
    assert r.target_met_chunk is None and r.complete
    assert len(r.target_checks) >= 1 and all(c["score"] < 500 for c in r.target_checks)
    assert int(np.asarray(r.episodes_done).min()) == 3  # every episode of the budget ran
    assert r.summary()["target_met_in_training"] is False


def test_without_the_stop_the_run_is_the_budget_and_no_check_runs():
    spec = resolve("CartPoleStayUp-v0", overrides={**FAST, "nepisodes": 4, "stop_at_target": False})
    assert Trainer(spec.env, spec.config).target_every() == 0
    r = train(spec.env, spec.config, spec.agent_params)
    assert r.target_checks is None and "target_met_in_training" not in r.summary()


def test_the_seed_preset_is_the_seeds_loop():
    assert resolve("CartPoleStayUp-v0", "seed").config.stop_at_target is False


def test_automatic_check_spacing_is_a_function_of_the_config():
    spec = resolve("CartPoleStayUp-v0", overrides={"n_envs": 64})
    c = spec.config
    every = Trainer(spec.env, c).target_every()
    # the worst case of a check (every episode to the horizon) is at most half the training between checks
    flights = (min(c.eval_envs, c.n_envs) + 1) * c.eval_episodes * 1000
    assert every * c.n_envs * c.chunk_steps >= 2 * flights and every * c.chunk_steps >= 2 * 1000
    assert Trainer(spec.env, c).target_every() == every


@pytest.mark.parametrize("env_id", ["ArmReach-v0", "QuadcopterGoto-v2", "QuadcopterGotoTwist-v0",
                                    "CartPoleStayUp-v0", "CartPoleContinuous-v0"])
def test_the_declared_task_fields_are_the_reset_states(env_id):
    """Whether a success-rate target is measurable is read from the task hook's annotation (no trace of the reset
    at start-up): where it names a dataclass, its fields are the traced reset's task fields."""
    import dataclasses

    import jaxrobo
    from jaxrobo.task.env import reset_shapes, task_fields

    env = jaxrobo.make(env_id)
    task = getattr(reset_shapes(env), "task", None)
    declared = task_fields(env)
    if dataclasses.is_dataclass(task):
        assert declared == tuple(f.name for f in dataclasses.fields(task))
    else:  # CartPoleContinuous-v0: a tuple, which no dataclass annotation describes
        assert declared is None


def test_an_env_without_a_declared_task_is_traced_for_its_target(monkeypatch):
    """Without the annotation (or wrapped), the trainer falls back to the reset's traced shapes: the same answer."""
    from jaxrobo.training import trainer as trainer_mod

    spec = resolve("ArmReach-v0", overrides={"n_envs": 4})
    traced, shapes = [], trainer_mod.reset_shapes
    monkeypatch.setattr(trainer_mod, "reset_shapes", lambda env: traced.append(env) or shapes(env))
    declared = Trainer(spec.env, spec.config).target_every()
    assert declared > 0 and not traced
    monkeypatch.setattr(trainer_mod, "task_fields", lambda env: None)
    assert Trainer(spec.env, spec.config).target_every() == declared and traced == [spec.env]


def test_deep_runs_stop_at_the_first_evaluation_that_meets_the_target():
    from jaxrobo.deep.training import target_met
    from jaxrobo.task.env import LearningTarget

    length = LearningTarget("up", "mean_length", 500.0, "")
    success = LearningTarget("arriving", "success_rate", 0.8, "")
    assert target_met({"length": np.array([600, 450])}, length)
    assert not target_met({"length": np.array([400, 450])}, length)
    assert target_met({"success": np.array([1, 1, 1, 0, 1])}, success)
    assert not target_met({"return": np.array([1.0])}, success)  # no arrivals recorded: never met
    assert not target_met({"length": np.array([600])}, None)


def test_defaults_sized_to_the_device(monkeypatch):
    on_cpu = resolve("QuadcopterGoto-v2")
    assert on_cpu.device_defaults == {} and on_cpu.config.n_envs == 16
    monkeypatch.setattr(run_mod, "accelerated", lambda: True)
    on_gpu = resolve("QuadcopterGoto-v2", check_memory=False)
    assert on_gpu.device_defaults == {"n_envs": 2048} and on_gpu.config.n_envs == 2048
    mine = resolve("QuadcopterGoto-v2", overrides={"n_envs": 32}, check_memory=False)
    assert mine.config.n_envs == 32 and mine.device_defaults == {}  # an explicit setting wins and is not listed
    # a saved run resolves to itself on any device (--resume on another machine)
    again = run_mod.spec_from_config(on_cpu.to_dict(), check_memory=False)
    assert again.config == on_cpu.config


def test_a_malformed_on_gpu_is_refused():
    with pytest.raises(ConfigError, match="on_gpu must be a mapping"):
        run_mod.device_overlay({"on_gpu": [1, 2]}, where="x")
    with pytest.raises(ConfigError, match="on_gpu must be a mapping"):
        run_mod.device_overlay({"on_gpu": {"env": {"a": 1}}}, where="x")


_DEVICES_SCRIPT = """
import hashlib, json, sys
import numpy as np
from jaxrobo.training.run import resolve
from jaxrobo.training.train import train
spec = resolve("CartPoleStayUp-v0", overrides=json.loads(sys.argv[1]))
r = train(spec.env, spec.config, spec.agent_params)
h = hashlib.sha256()
for a in (r.q, r.returns, r.lengths, r.eval_returns, r.eval_lengths):
    h.update(np.ascontiguousarray(np.asarray(a)).tobytes())
print(json.dumps({"met": r.target_met_chunk, "checks": [c["score"] for c in r.target_checks], "hash": h.hexdigest(),
                  "plan": r.plan}))
"""


@pytest.mark.slow
def test_the_stop_is_the_same_on_one_and_several_devices(tmp_path):
    """The checks fly the carry split over the devices as on one: the same scores, the same stop, the same bytes."""
    import json
    import os
    import subprocess
    import sys

    overrides = json.dumps({**FAST, "target_every": 2})
    out = []
    for n in (1, 4):
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": f"--xla_force_host_platform_device_count={n}"}
        proc = subprocess.run([sys.executable, "-c", _DEVICES_SCRIPT, overrides], env=env, capture_output=True,
                              text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        out.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    one, four = out
    assert "devices=4" in four["plan"] and "devices" not in one["plan"]
    assert one["met"] is not None and (one["met"], one["checks"], one["hash"]) == (four["met"], four["checks"],
                                                                                     four["hash"])
