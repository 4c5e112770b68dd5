"""Stable-Baselines3, a real client, on ``gym.make`` ids unchanged: SB3's own ``check_env`` and a tiny PPO run on
the CPU. SB3 needs PyTorch, which neither the default install nor the test extra carries: ``pip install
torch==2.13.0 -e ".[sb3]"`` (what CI's ``.ci/run`` installs, and why that torch) makes these run, else they skip
with the reason. In the slow tier: each id compiles its step, and PPO builds a torch policy."""
from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest

import jaxrobo  # noqa: F401  (registers the jaxrobo/<id> Gymnasium ids)

pytestmark = pytest.mark.slow

_MISSING = "SB3/PyTorch not installed (pip install torch==2.13.0 -e '.[sb3]'; see .ci/run)"
torch = pytest.importorskip("torch", reason=_MISSING)
sb3 = pytest.importorskip("stable_baselines3", reason=_MISSING)
from stable_baselines3.common.env_checker import check_env  # noqa: E402

CARTPOLE = "jaxrobo/CartPoleStayUp-v0"
TOTAL_STEPS = 256
N_STEPS = 64  # four rollouts, so PPO updates its policy four times


@pytest.mark.parametrize("gym_id", [CARTPOLE, "jaxrobo/QuadcopterGoto-v2"])
def test_sb3_check_env_passes_on_a_gym_make_id(gym_id):
    """SB3's checker (which also runs Gymnasium's) on what ``gym.make`` returns, its warnings errors: SB3 would
    warn about spaces or dtypes it cannot use."""
    env = gym.make(gym_id)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env)


@pytest.fixture(scope="module")
def trained():
    from stable_baselines3 import PPO

    env = gym.make(CARTPOLE)
    model = PPO("MlpPolicy", env, n_steps=N_STEPS, batch_size=32, n_epochs=1, policy_kwargs=dict(net_arch=[8]),
                seed=0, device="cpu")
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=TOTAL_STEPS)
    return model, before


def test_sb3_ppo_trains_through_gym_make(trained):
    model, before = trained
    assert model.num_timesteps == TOTAL_STEPS
    after = list(model.policy.parameters())
    assert any(not torch.equal(a, b) for a, b in zip(after, before))  # the updates reached the policy
    # SB3's Monitor saw the episodes the jaxrobo env ended (the pole falls within a few dozen steps at random)
    lengths = [info["l"] for info in model.ep_info_buffer]
    assert lengths and all(1 <= n <= 1000 for n in lengths) and sum(lengths) <= TOTAL_STEPS


def test_sb3_ppo_acts_in_the_env_and_a_saved_model_acts_the_same(trained, tmp_path):
    from stable_baselines3 import PPO

    model, _ = trained
    env = gym.make(CARTPOLE)
    obs, _ = env.reset(seed=3)
    observations = [obs]
    for _ in range(20):
        action, _ = model.predict(obs, deterministic=True)
        assert env.action_space.contains(int(action))
        obs, _, terminated, truncated, _ = env.step(action)
        observations.append(obs)
        if terminated or truncated:
            obs, _ = env.reset()
    batch = np.stack(observations)
    model.save(tmp_path / "ppo")
    loaded = PPO.load(tmp_path / "ppo.zip", device="cpu")
    np.testing.assert_array_equal(loaded.predict(batch, deterministic=True)[0],
                                  model.predict(batch, deterministic=True)[0])
