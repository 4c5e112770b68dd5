"""YAML configs: shipped files load and validate; overrides route to learner, loop or env; errors name the key."""
from __future__ import annotations

import jax.numpy as jnp
import pytest

import jaxrobo
from jaxrobo.core.config import ConfigError, load_yaml, parse_overrides
from jaxrobo.task.registry import registration
from jaxrobo.training.run import agent_presets, resolve


def test_every_registered_env_resolves_with_each_preset():
    for env_id in jaxrobo.registered():
        if jnp.issubdtype(registration(env_id).env_class().action_dtype, jnp.floating):
            continue  # continuous (Box) ids have no tabular presets: Brax's trainers learn them
        for preset in agent_presets(env_id) or {"default": {}}:
            spec = resolve(env_id, preset)
            assert spec.config.nepisodes >= 1 and 0 < spec.agent_params.alpha <= 1


def test_seed_preset_reproduces_the_seed_yaml():
    spec = resolve("CartPoleStayUp-v0", "seed")
    p, c = spec.agent_params, spec.config
    assert (p.alpha, p.gamma, p.epsilon, p.epsilon_discount) == (0.5, 0.9, 0.1, 0.999)
    assert (c.nepisodes, c.nsteps, c.number_splits, c.seed_compat, c.discretiser) == (1000, 1000, 10, True, "round")
    assert spec.env.options.round_obs


def test_overrides_route_by_key_and_by_prefix():
    spec = resolve("CartPoleStayUp-v0", overrides={"alpha": 0.3, "pos_step": 0.02, "env.init_pos": 0.1,
                                                   "agent.n_envs": 7})
    assert spec.agent_params.alpha == 0.3 and spec.config.n_envs == 7
    assert spec.env.default_params.pos_step == 0.02 and spec.env.default_params.init_pos == 0.1


@pytest.mark.parametrize("overrides,fragment", [
    ({"alfa": 0.1}, "unknown key 'alfa' (did you mean alpha"),
    ({"alpha": 1.5}, "alpha=1.5: expected a number > 0.0 and <= 1.0"),
    ({"gamma": "high"}, "gamma='high': expected a number"),
    ({"n_envs": 0}, "n_envs=0: expected an integer >= 1"),
    ({"agent": "dqn"}, "agent='dqn': allowed values are"),
    ({"seed_compat": "yes"}, "seed_compat='yes': expected a boolean"),
    ({"epsilon": float("nan")}, "must be finite"),
])
def test_bad_values_fail_before_compiling_with_the_key_named(overrides, fragment):
    with pytest.raises(ConfigError) as err:
        resolve("CartPoleStayUp-v0", overrides=overrides)
    assert fragment in str(err.value)


def test_unknown_preset_lists_the_allowed_ones():
    with pytest.raises(ConfigError, match="preset='fast': allowed values are default, seed"):
        resolve("CartPoleStayUp-v0", "fast")


def test_yaml_is_loaded_safely(tmp_path):
    bad = tmp_path / "evil.yaml"
    bad.write_text("env: !!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(Exception, match="could not determine a constructor|ConstructorError"):
        load_yaml(str(bad))
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_yaml(str(lst))


def test_command_line_values_parse_as_yaml():
    assert parse_overrides(["alpha=0.3", "seed_compat=true", "bins=[1, 2]", "agent=sarsa"]) == {
        "alpha": 0.3, "seed_compat": True, "bins": [1, 2], "agent": "sarsa"}
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        parse_overrides(["alpha"])


def test_a_saved_run_config_resolves_back_to_the_same_run():
    spec = resolve("CartPoleStayUp-v0", "seed", overrides={"alpha": 0.2, "pos_step": 0.02})
    saved = spec.to_dict()
    overrides = {**saved["agent_params"], **saved["train"]}
    overrides.update({f"env.{k}": v for k, v in {**saved["env_options"], **saved["env_params"]}.items()})
    again = resolve(saved["env_id"], saved["preset"], overrides)
    assert again.to_dict() == saved


def test_train_takes_what_resolve_gives_and_float32_copies_of_it():
    """train()'s checks of a Python caller's arguments (run.check_train_arguments) refuse no valid run: every
    resolved preset, its parameters as float32 arrays (a bound such as max_incl=1.6 is 1.60000002 in float32),
    a range as an array and a sweep's rows of parameters."""
    import numpy as np

    from jaxrobo.training.run import check_train_arguments

    for env_id in ("CartPoleStayUp-v0", "QuadcopterGoto-v2", "ArmReach-v0"):
        for preset in agent_presets(env_id):
            spec = resolve(env_id, preset)
            check_train_arguments(spec.env, spec.config, spec.agent_params, spec.env.default_params, start_chunk=0,
                                  checkpoint_every=3, checkpoint_seconds=None)
    spec = resolve("QuadcopterGoto-v2")
    ap = spec.agent_params.replace(alpha=jnp.float32(1.0), gamma=np.float32(0.99))
    ep = spec.env.default_params.replace(max_incl=np.float32(1.6), max_episode_steps=jnp.int32(50),
                                         rand_mass=jnp.array([0.9, 1.1]))
    check_train_arguments(spec.env, spec.config, ap, ep, checkpoint_seconds=0.5)
    rows = spec.env.default_params.replace(speed_value=jnp.array([0.5, 1.0, 5.0]))
    check_train_arguments(spec.env, spec.config, spec.agent_params, rows, population=True)
    with pytest.raises(ConfigError, match=r"train\(env_params\): speed_value=9.0: expected a number > 0.0"):
        check_train_arguments(spec.env, spec.config, spec.agent_params, rows.replace(speed_value=jnp.array([1., 9.])))


def test_deep_train_takes_every_resolved_preset():
    """deep.train's check of a Python caller's spec (deep.check_spec) refuses no spec that resolve gives."""
    from jaxrobo import deep

    checked = []
    for env_id in ("CartPoleContinuous-v0", "QuadcopterGotoTwist-v0"):
        for agent in deep.AGENTS:
            for preset in deep.presets(agent, env_id):
                deep.check_spec(deep.resolve(env_id, agent, preset))
                checked.append((env_id, agent, preset))
    # every agent has its presets on both tasks, the tiny one (the tests') and the default among them
    for env_id in ("CartPoleContinuous-v0", "QuadcopterGotoTwist-v0"):
        for agent in deep.AGENTS:
            assert {"default", "tiny"} <= {p for e, a, p in checked if (e, a) == (env_id, agent)}, (env_id, agent)
