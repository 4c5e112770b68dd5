"""The Gymnasium vector env's autoreset modes (NEXT_STEP, SAME_STEP, DISABLED) against Gymnasium's own SyncVectorEnv.

Each mode drives a :class:`JaxroboVectorEnv` and a ``SyncVectorEnv`` of single :class:`JaxroboEnv`s with the same
seeds and actions. Their randomness is the same (an unseeded reset continues the key the env's state carries in
both), so observations, rewards, flags, ``final_obs`` and the info masks are compared exactly, across episodes
that end both ways (terminated and truncated) at different steps in different envs. Gymnasium 1.3 has no
``check_env`` for vector envs; the contract checks below (metadata, spaces, dtypes, info masks) stand in for it.
"""
from __future__ import annotations

import warnings

import gymnasium as gym
import jax
import numpy as np
import pytest
from gymnasium.utils.env_checker import data_equivalence
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import jaxrobo  # noqa: F401 - registers the jaxrobo/<id> Gymnasium ids
from jaxrobo.interop.gym_adapter import JaxroboEnv, JaxroboVectorEnv, autoreset_mode_of

ID = "CartPoleStayUpLeftRight-v0"
N = 3  # the batch size of tests/test_gym_adapter.py: the same compiled steps serve both files
# Episodes that end fast both ways: the pole limit terminates, the step cap truncates.
SHORT = {"max_episode_steps": 6, "max_pole_angle": 0.03, "min_pole_angle": -0.03}
MODES = [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED]


def _pair(mode: AutoresetMode) -> tuple[JaxroboVectorEnv, SyncVectorEnv]:
    ours = JaxroboVectorEnv(ID, num_envs=N, overrides=SHORT, autoreset_mode=mode)
    ref = SyncVectorEnv([lambda: JaxroboEnv(ID, overrides=SHORT) for _ in range(N)], autoreset_mode=mode)
    return ours, ref


def _present(info: dict) -> dict:
    """``info`` without the keys no env has (mask all False): SyncVectorEnv leaves such a key out, jaxrobo keeps
    every key on every step (a stable structure) with its mask False."""
    out = {}
    for key, value in info.items():
        if key.startswith("_"):
            continue
        mask = info[f"_{key}"]
        if mask.any():
            out[key], out[f"_{key}"] = (_present(value) if isinstance(value, dict) else value), mask
    return out


def _same_step(ours_out: tuple, ref_out: tuple) -> None:
    for x, y in zip(ours_out[:4], ref_out[:4]):
        assert type(x) is type(y) and x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)
    a, b = _present(ours_out[4]), _present(ref_out[4])
    assert data_equivalence(a, b, exact=True), (a, b)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES, ids=lambda m: m.name)
def test_matches_sync_vector_env(mode):
    """Same seeds, same actions, every mode: JaxroboVectorEnv == SyncVectorEnv(JaxroboEnv) step for step. In
    DISABLED mode both reset the finished envs with ``reset_mask`` (unseeded, then seeded, then a list)."""
    ours, ref = _pair(mode)
    assert ours.metadata["autoreset_mode"] == ref.metadata["autoreset_mode"] == mode
    o1, _ = ours.reset(seed=9)
    o2, _ = ref.reset(seed=9)
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    ends, masked_resets = [], 0
    for t in range(24):
        a = rng.integers(2, size=N)
        r1, r2 = ours.step(a), ref.step(a)
        _same_step(r1, r2)
        done = r1[2] | r1[3]
        ends.append((r1[2].copy(), r1[3].copy()))
        if mode == AutoresetMode.SAME_STEP:
            assert ("final_obs" in r1[4]) == done.any()
            if done.any():
                # The returned observation is the next episode's first one; the final one is in the info.
                assert np.all(r1[4]["_final_obs"] == done) and np.all(r1[4]["_final_info"] == done)
                assert all(r1[4]["final_obs"][i] is None for i in np.flatnonzero(~done))
                assert not np.array_equal(np.stack(r1[4]["final_obs"][done]), r1[0][done])
        if mode == AutoresetMode.DISABLED and done.any():
            seed = [None, 100 + t, [1000 + i for i in range(N)]][masked_resets % 3]
            masked_resets += 1
            o1, i1 = ours.reset(seed=seed, options={"reset_mask": done.copy()})
            o2, i2 = ref.reset(seed=seed, options={"reset_mask": done.copy()})
            np.testing.assert_array_equal(o1, o2)
            assert data_equivalence(_present(i1), _present(i2), exact=True)
    terms = np.array([e[0] for e in ends])
    truncs = np.array([e[1] for e in ends])
    assert terms.any() and truncs.any()  # both kinds of episode end were crossed
    # Envs ended on different steps (the resets are per env, not of the whole batch).
    ended = terms | truncs
    assert any(0 < row.sum() < N for row in ended)
    if mode == AutoresetMode.DISABLED:
        assert masked_resets >= 3
    ours.close()
    ref.close()


def test_make_vec_takes_the_mode():
    """``gymnasium.make_vec(id, num_envs, autoreset_mode=...)``: the vector entry point takes its arguments as
    keywords (Gymnasium refuses ``vector_kwargs`` for it); ``vectorization_mode="sync"`` takes the same mode
    through ``vector_kwargs`` and gives the SyncVectorEnv this file compares with."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for mode in (AutoresetMode.SAME_STEP, "Disabled", "NEXT_STEP"):
            venv = gym.make_vec(f"jaxrobo/{ID}", num_envs=N, autoreset_mode=mode)
            assert isinstance(venv.unwrapped, JaxroboVectorEnv)
            assert venv.metadata["autoreset_mode"] == autoreset_mode_of(mode)
            assert isinstance(venv.metadata["autoreset_mode"], AutoresetMode)
            venv.close()
        sync = gym.make_vec(f"jaxrobo/{ID}", num_envs=N, vectorization_mode="sync",
                            vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})
    assert isinstance(sync, SyncVectorEnv) and sync.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    sync.close()
    assert JaxroboVectorEnv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP  # the default
    assert JaxroboVectorEnv(ID, num_envs=N).metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP


@pytest.mark.parametrize("bad", ["same_step", "SameStepp", 1, None, gym.envs.registration.VectorizeMode.SYNC])
def test_bad_mode_is_refused_before_anything_is_built(bad, monkeypatch):
    import jaxrobo.interop.gym_adapter as adapter

    monkeypatch.setattr(adapter, "_make_env", lambda *a, **k: pytest.fail("built an env for a bad mode"))
    with pytest.raises(ValueError, match=r"autoreset_mode=.*allowed values are AutoresetMode.NEXT_STEP \(or "
                                         r"'NextStep'\), AutoresetMode.SAME_STEP .*AutoresetMode.DISABLED"):
        JaxroboVectorEnv(ID, num_envs=N, autoreset_mode=bad)


def test_disabled_never_resets_by_itself_and_masks_reset_only_their_envs():
    venv = JaxroboVectorEnv(ID, num_envs=N, overrides=SHORT, autoreset_mode=AutoresetMode.DISABLED)
    first, _ = venv.reset(seed=3)
    done = np.zeros(N, bool)
    while not done.any():
        obs, _, term, trunc, info = venv.step(np.zeros(N, np.int64))
        done = term | trunc
        assert info["_steps"].all() and (info["steps"] >= 1).all()  # every env stepped, none was reset
    with pytest.raises(gym.error.ResetNeeded, match=r"envs \[.*\] finished .*reset_mask"):
        venv.step(np.zeros(N, np.int64))
    key_before = np.asarray(jax.random.key_data(venv.states.key))
    steps_before = np.asarray(venv.states.steps)
    after, info = venv.reset(options={"reset_mask": done})
    assert info == {}
    np.testing.assert_array_equal(after[~done], obs[~done])  # the others keep their state
    np.testing.assert_array_equal(np.asarray(venv.states.steps)[~done], steps_before[~done])
    assert (np.asarray(venv.states.steps)[done] == 0).all()
    # Fresh randomness: not the episode's cached first state, and a new key.
    assert not np.array_equal(after[done], first[done])
    key_after = np.asarray(jax.random.key_data(venv.states.key))
    assert not (key_after[done] == key_before[done]).all(axis=-1).any()
    venv.step(np.zeros(N, np.int64))  # steps again


def test_reset_mask_is_checked():
    venv = JaxroboVectorEnv(ID, num_envs=N, autoreset_mode=AutoresetMode.DISABLED)
    with pytest.raises(gym.error.ResetNeeded, match="without a mask first"):
        venv.reset(options={"reset_mask": np.array([True, False, False])})
    venv.reset(seed=0)
    for bad, match in [(np.array([1, 0, 0]), "dtype int64"), (np.array([True, False]), r"shape \(2,\)"),
                       (np.zeros(N, bool), "selects no env")]:
        with pytest.raises(ValueError, match=match):
            venv.reset(options={"reset_mask": bad})
    with pytest.raises(ValueError, match="init_pole_angle.*shared by every env"):
        venv.reset(options={"reset_mask": np.array([True, False, False]), "init_pole_angle": 0.1})
    with pytest.raises(ValueError, match="2 seeds for 3 envs"):
        venv.reset(seed=[1, 2], options={"reset_mask": np.array([True, False, False])})
    # A mask works in the other modes too; the caller's options dict is left as it was.
    options = {"reset_mask": np.array([False, True, False])}
    nxt = JaxroboVectorEnv(ID, num_envs=N)
    obs, _ = nxt.reset(seed=5)
    again, _ = nxt.reset(seed=[None, 6, None], options=options)
    assert "reset_mask" in options
    np.testing.assert_array_equal(again, obs)  # env 1 reset from seed 6: the same state seed=5 gave it


def _check_masks(info: dict, mode: AutoresetMode) -> None:
    for key in [k for k in info if not k.startswith("_")]:
        mask = info[f"_{key}"]
        assert mask.dtype == np.bool_ and mask.shape == (N,), (mode, key)
        if isinstance(info[key], dict):
            _check_masks(info[key], mode)
        else:
            assert len(info[key]) == N, (mode, key)


def test_vector_contract_in_every_mode():
    """What a vector env checker would check: batched spaces, dtypes and shapes, seeding, metadata, one info
    mask per info key, in every mode."""
    for mode in MODES:
        venv = JaxroboVectorEnv(ID, num_envs=N, overrides=SHORT, autoreset_mode=mode)
        assert venv.observation_space == gym.vector.utils.batch_space(venv.single_observation_space, N)
        assert venv.action_space == gym.vector.utils.batch_space(venv.single_action_space, N)
        o1, _ = venv.reset(seed=42)
        o2, _ = venv.reset(seed=42)
        assert data_equivalence(o1, o2, exact=True) and o1 in venv.observation_space
        venv.action_space.seed(0)
        for _ in range(10):
            obs, rew, term, trunc, info = venv.step(venv.action_space.sample())
            assert obs in venv.observation_space and obs.dtype == np.float32
            assert rew.dtype == np.float64 and term.dtype == trunc.dtype == np.bool_
            _check_masks(info, mode)
            if mode == AutoresetMode.DISABLED and (term | trunc).any():
                venv.reset(options={"reset_mask": term | trunc})
        venv.close()


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.DISABLED], ids=lambda m: m.name)
def test_gymnasium_episode_statistics_wrapper_counts_our_episodes(mode):
    """Gymnasium's ``RecordEpisodeStatistics`` vector wrapper over the env (it reads ``reset_mask`` from the
    options after the env's reset: jaxrobo leaves the caller's options as they were) counts each episode as long
    as the env's own step counter says."""
    venv = gym.wrappers.vector.RecordEpisodeStatistics(
        JaxroboVectorEnv(ID, num_envs=N, overrides=SHORT, autoreset_mode=mode))
    venv.reset(seed=4)
    rng = np.random.default_rng(2)
    episodes = 0
    for _ in range(20):
        _, rew, term, trunc, info = venv.step(rng.integers(2, size=N))
        done = term | trunc
        if done.any():
            episodes += int(done.sum())
            np.testing.assert_array_equal(info["episode"]["l"][done], info["steps"][done])
            if mode == AutoresetMode.DISABLED:
                venv.reset(options={"reset_mask": done})
    assert episodes >= N and venv.episode_count == episodes
