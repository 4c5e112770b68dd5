"""``jaxrobo train --agent ppo|sac`` (Brax's trainers on the env's Brax face), its run directory, the saved
policy, ``jaxrobo show`` and ``jaxrobo plot`` of such runs. CPU-sized: the ``tiny`` presets with fewer steps."""
from __future__ import annotations

import csv
import json
import os
import re
import shutil

import numpy as np
import pytest

from jaxrobo.cli import main

CPC, TWIST = "CartPoleContinuous-v0", "QuadcopterGotoTwist-v0"
#: On top of the ``tiny`` preset: the fewest steps that still run two evaluation points.
SMALL = ("--set", "episode_length=20", "--set", "eval_episodes=3", "--set", "num_timesteps=512")
RUN_FILES = ("config.yaml", "status.json", "summary.json", "evaluations.csv", "episode_stats.csv",
             "policy.npz", "policy.json", "rewards.png", "tensorboard")


def _train(out: str, env_id: str, agent: str = "ppo", *extra: str) -> None:
    code = main(["train", "--env", env_id, "--agent", agent, "--preset", "tiny", *SMALL, *extra, "--out", out,
                 "--no-progress"])
    assert code == 0


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("deep")
    out = {}
    for env_id in (CPC, TWIST):
        out[env_id] = str(root / env_id)
        _train(out[env_id], env_id)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("env_id", [CPC, TWIST])
def test_a_tiny_ppo_run_writes_a_complete_run_directory(runs, env_id):
    d = runs[env_id]
    for name in RUN_FILES:
        assert os.path.exists(os.path.join(d, name)), name
    status = json.load(open(os.path.join(d, "status.json")))
    assert status["status"] == "complete"
    summary = json.load(open(os.path.join(d, "summary.json")))
    assert summary["agent"] == "ppo" and summary["env_id"] == env_id
    assert summary["env_steps"] >= 512 and summary["evaluations"] == 2
    with open(os.path.join(d, "evaluations.csv")) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 3  # two evaluation points x eval_episodes
    assert all(1 <= int(r["length"]) <= 20 for r in rows)
    with open(os.path.join(d, "episode_stats.csv")) as f:
        stats = list(csv.DictReader(f))
    assert [int(s["env_steps"]) for s in stats] == [0, summary["env_steps"]]
    if env_id == TWIST:  # the Goto counts arrivals as the tabular evaluation does
        assert "success" in rows[0] and "final_eval_success_rate" in summary
    # the saved config resolves to itself (jaxrobo show rebuilds the run from it)
    from jaxrobo import deep
    from jaxrobo.io.results import load_config

    cfg = load_config(d)
    assert deep.spec_from_config(cfg).to_dict() == json.loads(json.dumps(cfg))


@pytest.mark.slow
def test_a_tiny_sac_run_completes(tmp_path):
    d = str(tmp_path / "sac")
    _train(d, CPC, "sac", "--set", "min_replay_size=32")
    summary = json.load(open(os.path.join(d, "summary.json")))
    assert summary["agent"] == "sac" and summary["evaluations"] == 2
    from jaxrobo import deep

    policy = deep.load_policy(d)
    assert policy.net["agent"] == "sac"
    a = np.asarray(policy.act(np.zeros(4, np.float32)))
    assert a.shape == (1,) and np.all(np.abs(a) <= 1.0)


@pytest.mark.parametrize("agent", ["ppo", "sac"])
def test_a_saved_policy_loads_back_and_acts_the_same(tmp_path, agent):
    """save_policy/load_policy round trip (plain npz by key path + JSON; no pickle): same actions."""
    import jax

    from jaxrobo import deep
    from jaxrobo.deep.policy import _networks, _template

    net = {"format": 1, "agent": agent, "observation_size": 5, "action_size": 2, "normalize_observations": True,
           "env_id": CPC}
    net.update({"policy_hidden_layer_sizes": [8, 8], "value_hidden_layer_sizes": [8]} if agent == "ppo"
               else {"hidden_layer_sizes": [8, 8]})
    template = _template(net)
    leaves, treedef = jax.tree.flatten(template)
    rng = np.random.default_rng(0)
    # Non-trivial values everywhere (normaliser included), so a mixed-up leaf would change the actions.
    params = jax.tree.unflatten(treedef, [np.asarray(rng.uniform(0.5, 1.5, np.shape(x)), np.asarray(x).dtype)
                                          for x in leaves])
    deep.save_policy(str(tmp_path), params, net)
    with np.load(tmp_path / "policy.npz", allow_pickle=False) as npz:  # plain arrays only
        assert len(npz.files) == len(leaves)
    loaded = deep.load_policy(str(tmp_path))
    _, make_policy = _networks(net)
    obs = rng.normal(size=(16, 5)).astype(np.float32)
    want = make_policy(params, deterministic=True)(obs, jax.random.key(0))[0]
    got = loaded.act(obs)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_a_loaded_policy_pickles_and_refuses_an_observation_of_another_size(tmp_path):
    """A LoadedPolicy goes through pickle (a process pool's argument; Brax's inference function is a closure pickle
    could not name) and acts the same after; act takes a list, and an observation of the wrong size is a
    ValueError naming both sizes (it was a broadcast error inside Brax's normaliser)."""
    import pickle

    from jaxrobo import deep
    from jaxrobo.deep.policy import _template

    net = {"format": 1, "agent": "ppo", "observation_size": 5, "action_size": 2, "normalize_observations": True,
           "policy_hidden_layer_sizes": [8], "value_hidden_layer_sizes": [8], "env_id": CPC}
    deep.save_policy(str(tmp_path), _template(net), net)
    policy = deep.load_policy(str(tmp_path))
    obs = np.random.default_rng(0).normal(size=(4, 5)).astype(np.float32)
    again = pickle.loads(pickle.dumps(policy))
    np.testing.assert_array_equal(np.asarray(again.act(obs)), np.asarray(policy.act(obs)))
    np.testing.assert_array_equal(np.asarray(policy.act(obs[0].tolist())), np.asarray(policy.act(obs[0])))
    for bad in (np.zeros(3, np.float32), np.zeros((2, 7), np.float32), 0.5):
        with pytest.raises(ValueError, match=r"this policy takes observations of size 5"):
            policy.act(bad)


def test_a_policy_that_does_not_match_its_networks_is_refused(tmp_path):
    from jaxrobo import deep
    from jaxrobo.deep.policy import _template
    from jaxrobo.core.config import ConfigError

    net = {"format": 1, "agent": "ppo", "observation_size": 3, "action_size": 1, "normalize_observations": False,
           "policy_hidden_layer_sizes": [4], "value_hidden_layer_sizes": [4], "env_id": CPC}
    deep.save_policy(str(tmp_path), _template(net), net)
    net["policy_hidden_layer_sizes"] = [6]
    with open(tmp_path / "policy.json", "w") as f:
        json.dump(net, f)
    with pytest.raises(ConfigError, match="has shape"):
        deep.load_policy(str(tmp_path))


def test_an_unknown_key_in_a_deep_run_config_is_named_as_the_file_s_not_a_set():
    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError

    cfg = deep.resolve(CPC, "ppo", "tiny").to_dict()
    cfg["train"]["bogus_key"] = 1
    with pytest.raises(ConfigError) as err:
        deep.spec_from_config(cfg, "run/config.yaml")
    assert str(err.value).startswith("run/config.yaml: (ppo on CartPoleContinuous-v0): unknown key 'bogus_key'")
    assert "--set" not in str(err.value)


@pytest.mark.parametrize("change, fragment", [
    ({"policy_hidden_layer_sizes": [-4]}, "policy_hidden_layer_sizes=[-4]: expected a non-empty list of integers"),
    ({"normalize_observations": "yes"}, "normalize_observations='yes': expected true or false"),
    ({"observation_size": 3.0}, "observation_size=3.0: expected an integer >= 1"),
    ({"nan_weight": True}, "has 1 non-finite values (NaN or inf)"),
    ({"zero_std": True}, "0/std holds values <= 0"),
])
def test_a_tampered_policy_is_refused_naming_the_field(tmp_path, change, fragment):
    """A hand-edited policy.json (a negative layer width was a traceback inside Brax; a string flag was taken as
    true) or a policy.npz of NaN weights or a zero normaliser std (flown and exported as a policy) is refused."""
    from jaxrobo import deep
    from jaxrobo.deep.policy import _template
    from jaxrobo.core.config import ConfigError

    net = {"format": 1, "agent": "ppo", "observation_size": 3, "action_size": 1, "normalize_observations": True,
           "policy_hidden_layer_sizes": [4], "value_hidden_layer_sizes": [4], "env_id": CPC}
    deep.save_policy(str(tmp_path), _template(net), net)
    arrays = dict(np.load(tmp_path / "policy.npz"))
    if change.pop("nan_weight", False):
        arrays["1/params/hidden_0/kernel"][0, 0] = np.nan
    if change.pop("zero_std", False):
        arrays["0/std"][:] = 0
    np.savez(tmp_path / "policy.npz", **arrays)
    with open(tmp_path / "policy.json", "w") as f:
        json.dump({**net, **change}, f)
    with pytest.raises(ConfigError, match=re.escape(fragment)):
        deep.load_policy(str(tmp_path))


def test_the_fields_both_trainers_take_are_declared_once_on_their_base():
    """Each shared field's type, range and doc live on DeepConfig; each trainer's config keeps them (its own
    default where the trainers differ) and a bad value is refused naming the field and its range."""
    import dataclasses

    from jaxrobo import deep
    from jaxrobo.core.config import ConfigError
    from jaxrobo.core.struct import rules

    shared = {f.name for f in dataclasses.fields(deep.DeepConfig)} - {"agent"}
    assert {"total_steps", "num_envs", "episode_length", "learning_rate", "batch_size", "seed"} <= shared
    for cls in (deep.PPOConfig, deep.SACConfig):
        assert issubclass(cls, deep.DeepConfig)
        assert all(rules(cls)[name] is rules(deep.DeepConfig)[name] for name in shared)
    with pytest.raises(ConfigError, match=r"learning_rate=0\.0: expected a number > 0\.0 and <= 1\.0"):
        deep.resolve(CPC, "sac", "tiny", {"learning_rate": 0})


def test_show_flies_a_saved_ppo_policy(runs, tmp_path, capsys):
    for env_id, flown in ((CPC, "2 episodes: mean return"), (TWIST, f"wrote {tmp_path / TWIST}.png")):
        png = str(tmp_path / f"{env_id}.png")
        assert main(["show", runs[env_id], "--out", png, "--episodes", "2"]) == 0
        out = capsys.readouterr().out
        assert "policy: ppo latest policy" in out and flown in out and os.path.getsize(png) > 0, out
    # the policy is the run's: without its parameters show refuses, naming the file
    bare = str(tmp_path / "bare")
    shutil.copytree(runs[CPC], bare)
    os.remove(os.path.join(bare, "policy.npz"))
    assert main(["show", bare, "--out", str(tmp_path / "none.png")]) == 2
    assert "no policy.npz" in capsys.readouterr().err


def test_plot_overlays_a_tabular_and_a_ppo_run_on_env_steps(runs, tmp_path):
    from jaxrobo.pictures.plots import env_steps_axis
    from jaxrobo.io.results import load_stats

    tab = str(tmp_path / "tab")
    assert main(["train", "--env", "CartPoleStayUp-v0", "--n-envs", "2", "--nepisodes", "5", "--set", "nsteps=30",
                 "--set", "eval_episodes=0", "--set", "chunk_steps=30", "--out", tab, "--no-progress"]) == 0
    png = str(tmp_path / "overlay.png")
    assert main(["plot", tab, runs[CPC], "--out", png]) == 0
    assert os.path.getsize(png) > 0
    stats = load_stats(tab)
    steps = env_steps_axis(tab, stats)
    np.testing.assert_allclose(steps, np.cumsum(stats["length_mean"]) * 2)
    ppo_steps = env_steps_axis(runs[CPC], load_stats(runs[CPC]))
    assert ppo_steps[0] == 0 and ppo_steps[-1] >= 512


def test_list_names_the_deep_agents(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "ppo, sac" in out and CPC in out and TWIST in out
