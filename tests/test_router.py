"""One config router for train and sweep, every default in one home, the learning target from the task."""
from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

import jaxrobo
from jaxrobo.tabular.learner import AgentParams
from jaxrobo.task import registry
from jaxrobo.training import sweep
from jaxrobo.core.config import ConfigError, load_yaml, split_and_validate
from jaxrobo.task.env import LearningTarget
from jaxrobo.training.run import agent_presets, resolve, route
from jaxrobo.training.trainer import TrainConfig
from jaxrobo.training.summary import TrainResult

CP = "CartPoleStayUp-v0"
IDS = ("CartPoleStayUp-v0", "CartPoleStayUpLeftRight-v0", "QuadcopterGoto-v1", "QuadcopterLiveShow-v0")
#: ``resolve(id, preset[, agent]).to_dict()`` of every id and preset as they resolved before the presets were cut
#: down to what differs from the defaults (regenerate only for an intended change: see _resolved_now).
RESOLVED = os.path.join(os.path.dirname(__file__), "data", "resolved_configs.json")


def _defaults(cls: type) -> dict:
    return {f.name: f.default if f.default is not dataclasses.MISSING else f.default_factory()
            for f in dataclasses.fields(cls)}


# ---- one router ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("key, where, static", [
    ("alpha", "agent", False), ("agent.gamma", "agent", False), ("nepisodes", "train", True),
    ("agent.n_envs", "train", True), ("running_step", "option", True), ("env.backend", "option", True),
    ("pos_step", "env", False), ("env.max_episode_steps", "env", False)])
def test_train_and_sweep_route_a_key_the_same_way(key, where, static):
    r = route(CP, key)
    assert (r.where, r.static) == (where, static)
    assert sweep.classify(CP, key) == r  # the sweep asks the same router
    value = {"alpha": 0.3, "gamma": 0.8, "nepisodes": 7, "n_envs": 3, "running_step": 0.08, "backend": "analytic",
             "pos_step": 0.02, "max_episode_steps": 50}[r.name]
    spec = resolve(CP, overrides={key: value}, check_memory=False)
    home = {"agent": spec.agent_params, "train": spec.config, "option": spec.env.options,
            "env": spec.env.default_params}[where]
    got = getattr(home, r.name)
    assert (got == value) if isinstance(value, str) else float(got) == pytest.approx(value)


def test_a_forced_side_without_the_key_fails_naming_where_it_lives():
    with pytest.raises(ConfigError, match=r"unknown key 'backend'.*backend is an env key: env.backend"):
        resolve(CP, overrides={"agent.backend": "mjx"}, check_memory=False)
    with pytest.raises(ConfigError, match=r"sweep: unknown key 'alpha'.*learner/loop key: agent.alpha"):
        sweep.classify(CP, "env.alpha")
    with pytest.raises(ConfigError, match="the seed is not a swept parameter"):
        sweep.classify(CP, "agent.seed")


# ---- every default in one home ---------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", IDS)
def test_no_yaml_key_repeats_its_default(env_id):
    reg = registry._lookup(env_id)
    cls = reg.env_class()
    env_defaults = {**_defaults(cls.Options), **_defaults(cls.Params), **reg.defaults}
    learner_defaults = {**_defaults(AgentParams), **_defaults(TrainConfig)}
    env_yaml = load_yaml(reg.spec.config).get("env") or {}
    options, params = split_and_validate(env_yaml, cls.Options, cls.Params)
    assert not [k for k, v in {**options, **params}.items() if v == env_defaults[k]], reg.spec.config
    for name, preset in agent_presets(env_id).items():
        preset = dict(preset or {})
        env = preset.pop("env", None) or {}
        on_gpu = preset.pop("on_gpu", None) or {}  # the sizes an accelerator takes instead of the preset's own
        agent_kw, train_kw = split_and_validate(preset, AgentParams, TrainConfig)
        assert not [k for k, v in {**agent_kw, **train_kw}.items() if v == learner_defaults[k]], name
        gpu_agent, gpu_train = split_and_validate(on_gpu, AgentParams, TrainConfig)
        assert not [k for k, v in {**gpu_agent, **gpu_train}.items()
                    if v == {**learner_defaults, **agent_kw, **train_kw}[k]], f"{name}: on_gpu"
        o, p = split_and_validate(env, cls.Options, cls.Params)
        assert not [k for k, v in {**o, **p}.items() if v == env_defaults[k]], name


def _resolved_now() -> dict:
    out = {}
    for env_id in IDS:
        for preset in agent_presets(env_id):
            out[f"{env_id}/{preset}"] = resolve(env_id, preset, check_memory=False).to_dict()
            for agent in ("sarsa", "double_q"):
                try:
                    out[f"{env_id}/{preset}/{agent}"] = resolve(env_id, preset, agent=agent,
                                                                check_memory=False).to_dict()
                except ConfigError:  # the seed presets refuse a learner with no seed form
                    pass
    return json.loads(json.dumps(out))


def test_every_preset_resolves_as_recorded():
    with open(RESOLVED) as f:
        recorded = json.load(f)
    now = _resolved_now()
    assert sorted(now) == sorted(recorded)
    for case, config in recorded.items():
        assert now[case] == config, case


@pytest.mark.parametrize("env_id", IDS)
def test_the_step_limit_has_one_source(env_id):
    params = registry._lookup(env_id).env_class().Params
    steps = _defaults(params)["max_episode_steps"]
    assert "max_episode_steps" not in registry.env_config(env_id)  # neither the registration nor the YAML repeat it
    assert jaxrobo.spec(env_id).max_episode_steps == steps
    assert jaxrobo.make(env_id).spec.max_episode_steps == steps


def test_a_registration_may_override_the_step_limit(monkeypatch):
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    registry.register("ShortCartPole-v0", "envs.cartpole.stay_up:CartPoleStayUp", 7, backend="analytic")
    assert jaxrobo.spec("ShortCartPole-v0").max_episode_steps == 7
    assert jaxrobo.make("ShortCartPole-v0").default_params.max_episode_steps == 7
    assert jaxrobo.make("ShortCartPole-v0", max_episode_steps=9).spec.max_episode_steps == 9


# ---- the learning target comes from the task -------------------------------------------------------------------
def _result(env_id: str, eval_lengths: list[list[int]], eval_returns: list[list[float]] | None = None) -> TrainResult:
    lengths = np.array([[3, 5]])
    ev = np.asarray(eval_lengths)
    return TrainResult(
        env_id, TrainConfig(n_envs=1, nepisodes=2), AgentParams(), lengths.astype(np.float32), lengths,
        np.ones_like(lengths, bool), np.ones(2, np.float32), np.zeros(1, np.int32), 8, np.zeros((1, 1, 2, 2)), 0.0, 1.0,
        eval_returns=ev.astype(np.float32) if eval_returns is None else np.asarray(eval_returns, np.float32),
        eval_lengths=ev, learning_target=registry._lookup(env_id).env_class().learning_target)


def test_the_summary_measures_the_tasks_declared_target():
    s = _result(CP, [[600, 500], [400, 500], [1000, 1000]]).summary()  # per-table means 550, 450, 1000
    assert s["eval_share_of_tables_over_500"] == pytest.approx(2 / 3)
    assert s["learning_target"] == "mean greedy episode length >= 500 steps"
    goto = _result("QuadcopterGoto-v1", [[600, 500]]).summary()
    assert "over_500" not in " ".join(goto) and "arriving" in goto["learning_target"]
    assert not [k for k in goto if k.startswith("eval_share_of_tables")]  # arrival is not in the trainer's record
    live = _result("QuadcopterLiveShow-v0", [[100, 100]]).summary()
    assert "learning_target" not in live and not [k for k in live if k.startswith("eval_share_of_tables")]


def test_a_target_on_the_return_is_measured_from_the_evaluation_returns():
    r = _result(CP, [[1, 1], [1, 1]], eval_returns=[[10.0, 30.0], [0.0, 10.0]])  # means 20 and 5
    r = dataclasses.replace(r, learning_target=LearningTarget("scoring", "mean_return", 15.0, "mean return >= 15"))
    assert r.summary()["eval_share_of_tables_scoring"] == 0.5
    with pytest.raises(ValueError, match="metric='steps'"):
        LearningTarget("x", "steps", 1.0, "")
