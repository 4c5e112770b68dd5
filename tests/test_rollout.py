"""Rollouts and autoreset: one greedy tie-breaking rule for every policy evaluation, episode lengths of a fixed
policy, and the one autoreset (fresh randomness, done envs only, gathered path == select path)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from jaxrobo.tabular import learner as tabular
from jaxrobo.task import autoreset, rollout

HORIZON = 30


@pytest.fixture(scope="module")
def cartpole():
    return jaxrobo.make("CartPoleStayUp-v0", backend="analytic")


# ---- the tie-breaking rule ------------------------------------------------------------------------------------
def test_greedy_policy_breaks_ties_at_random_by_the_step_key():
    """Among equal maxima the step key picks (uniformly), never a smaller value: ``tabular.greedy``'s rule."""
    q = jnp.asarray([[[1.0, 3.0, 3.0, 0.0, 3.0]]])  # one table, one state, three tied maxima
    policy = rollout.greedy_policy(q, lambda obs: jnp.int32(0))
    keys = jax.random.split(jax.random.key(0), 600)
    actions = np.asarray(jax.vmap(lambda k: policy(k, jnp.zeros(4)))(keys))
    assert set(np.unique(actions)) == {1, 2, 4}
    assert np.all(np.abs(np.bincount(actions, minlength=5)[[1, 2, 4]] - 200) < 60)
    np.testing.assert_array_equal(actions, np.asarray(jax.vmap(lambda k: tabular.greedy(k, q[0, 0]))(keys)))


def test_greedy_policy_acts_on_the_sum_of_double_q_tables():
    q = jnp.asarray([[[0.0, 2.0, 0.0]], [[3.0, 0.0, 0.0]]])  # table 0 says 1, table 1 says 0, their sum says 0
    policy = rollout.greedy_policy(q, lambda obs: jnp.int32(0))
    assert int(policy(jax.random.key(1), jnp.zeros(2))) == 0
    with pytest.raises(ValueError, match="n_tables, n_states, n_actions"):
        rollout.greedy_policy(q[0], lambda obs: 0)


def test_trainer_evaluate_is_the_greedy_rollout_with_its_key_layout(cartpole):
    """``Trainer.evaluate`` = the documented key layout with ``tabular.greedy`` at every step (the reference
    below is the trainer's evaluation as it was written before the rollout module, so its figures stay the same)."""
    from jaxrobo.training.run import resolve
    from jaxrobo.training.trainer import Trainer

    spec = resolve("CartPoleStayUp-v0", overrides={"backend": "analytic", "n_envs": 1, "bins": [3, 3, 4, 4],
                                                   "state_low": [-2.4, -1.0, -0.3, -2.0],
                                                   "state_high": [2.4, 1.0, 0.3, 2.0]})
    env, trainer = spec.env, Trainer(spec.env, spec.config)
    n_states = trainer.disc.n_states
    # Small integers: many ties, so the rule matters.
    q = jax.random.randint(jax.random.key(7), (1, n_states, env.num_actions), 0, 2).astype(jnp.float32)
    agent = tabular.AgentState(q, None)
    params = env.default_params

    def reference(key):
        def episode(k):
            k_reset, k_run = jax.random.split(k)
            state = env.reset(k_reset, params)

            def body(carry, k_step):
                state, ret, length, alive = carry
                a = tabular.greedy(k_step, tabular.action_values(agent, trainer.disc(state.obs)))
                nxt = env.step(state, a, params)
                return (nxt, ret + jnp.where(alive, nxt.reward, 0.0), length + alive.astype(jnp.int32),
                        alive & ~nxt.done), None

            init = (state, jnp.float32(0), jnp.int32(0), jnp.bool_(True))
            (_, ret, length, _), _ = jax.lax.scan(body, init, jax.random.split(k_run, HORIZON))
            return ret, length

        return jax.vmap(episode)(jax.random.split(key, 8))

    key = jax.random.key(3)
    got = jax.jit(lambda k: trainer.evaluate(k, agent, 8, params, HORIZON))(key)
    want = jax.jit(reference)(key)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert len(set(np.asarray(got[1]).tolist())) > 1  # the episodes differ: the test is not vacuous


def test_a_rollout_in_segments_is_the_one_scan_rollout_bit_for_bit(cartpole):
    """The evaluation's segments (a progress line between them) fly the same episodes: the same keys, steps
    and figures, byte for byte, a segment length that does not divide the horizon included; the flight may end
    early once no episode runs."""
    from jaxrobo.training import driver

    policy = rollout.random_policy(cartpole.num_actions)
    key, params = jax.random.key(11), cartpole.default_params
    want = jax.device_get(rollout.outcomes(jax.jit(lambda k: rollout.rollout(cartpole, policy, k, 6, HORIZON))(key)))
    carry = jax.jit(lambda k: rollout.rollout_start(cartpole, k, 6, params))(key)
    advance = jax.jit(lambda c, t0: rollout.rollout_advance(cartpole, policy, c, t0, 7, HORIZON, params))
    for t0 in range(0, HORIZON, 7):
        carry = advance(carry, np.int32(t0))
    got = jax.device_get(rollout.outcomes(rollout.rollout_end(carry)))
    assert set(got) == set(want) and len(set(want["length"].tolist())) > 1
    for k in want:
        assert np.asarray(got[k]).tobytes() == np.asarray(want[k]).tobytes(), k
    assert driver.EvalProgress("tables", 3, 10, 2, 4, 6.0).eta == pytest.approx(14.0)
    assert driver.EvalProgress("tables", 3, 10, 0, 4, 6.0).eta == 0.0


def test_render_q_policy_breaks_ties_by_the_same_rule():
    """The video policy ties like the trainer's evaluation (random among maxima, from the step's key), not by
    taking the first maximum: an untrained (all-zero) table does not always push the same way."""
    from jaxrobo.pictures import render

    q = np.zeros((1, 2, 4), np.float32)
    q[0, 1] = [0.0, 2.0, 1.0, 2.0]  # state 1: actions 1 and 3 tie
    state_of = lambda obs: (obs[0] > 0).astype(jnp.int32)  # noqa: E731
    policy = render.q_policy(q, state_of, seed=5)
    tied = [policy(np.array([1.0])) for _ in range(40)]
    assert set(tied) == {1, 3}
    keys = [jax.random.fold_in(jax.random.key(5), t) for t in range(40)]
    assert tied == [int(tabular.greedy(k, jnp.asarray(q[0, 1]))) for k in keys]
    untrained = render.q_policy(q[0], state_of, seed=0)  # a [n_states, n_actions] table works too
    assert len({untrained(np.array([-1.0])) for _ in range(40)}) == 4
    again = render.q_policy(q, state_of, seed=5)
    assert [again(np.array([1.0])) for _ in range(40)] == tied  # same seed, same choices


# ---- rollouts -------------------------------------------------------------------------------------------------
def _host_lengths(env, policy_action, keys, horizon):
    """Episode lengths and returns stepped one by one on the host, the obvious way."""
    step = jax.jit(env.step)
    lengths, returns = [], []
    for k in keys:
        k_reset, _ = jax.random.split(k)
        state, total, n = env.reset(k_reset), 0.0, 0
        while n < horizon:
            state = step(state, jnp.int32(policy_action))
            total += float(state.reward)
            n += 1
            if bool(state.done):
                break
        lengths.append(n)
        returns.append(total)
    return np.array(lengths), np.array(returns, np.float32)


def test_fixed_policy_rollout_gives_the_episode_lengths_on_the_cartpole(cartpole):
    """Always pushing right (the big step) topples the pole or runs off the track within the horizon; the
    rollout's lengths and returns are those of stepping each episode by hand, and the last state is the end."""
    env = cartpole
    policy = lambda k, obs: jnp.int32(3)  # noqa: E731
    key = jax.random.key(11)
    out = jax.jit(lambda k: rollout.rollout(env, policy, k, 4, HORIZON, observe=lambda s: s.obs))(key)
    want_len, want_ret = _host_lengths(env, 3, jax.random.split(key, 4), HORIZON)
    np.testing.assert_array_equal(np.asarray(out["length"]), want_len)
    np.testing.assert_array_equal(np.asarray(out["return"]), want_ret)  # reward 1 per step
    assert np.all(want_len < HORIZON) and np.all(np.asarray(out["last"].terminated))
    np.testing.assert_array_equal(np.asarray(out["last"].steps), want_len)
    alive = np.asarray(out["alive"])
    assert alive.shape == (4, HORIZON + 1) and np.array_equal(alive.sum(axis=1), want_len + 1)
    trace = np.asarray(out["trace"])  # frozen at the end: the last recorded observation is the last state's
    np.testing.assert_array_equal(trace[:, -1], np.asarray(out["last"].obs))
    np.testing.assert_array_equal(trace[:, 0], np.asarray(out["first"].obs))

    short = jax.jit(lambda k: rollout.rollout(env, policy, k, 4, 3))(key)  # the horizon caps the lengths
    np.testing.assert_array_equal(np.asarray(short["length"]), np.minimum(want_len, 3))


def test_rollout_horizon_defaults_to_the_spec_and_is_checked(cartpole):
    with pytest.raises(ValueError, match="horizon=0"):
        rollout.rollout(cartpole, rollout.random_policy(4), jax.random.key(0), 2, 0)
    shape = jax.eval_shape(lambda k: rollout.rollout(cartpole, rollout.random_policy(4), k, 2,
                                                     observe=lambda s: s.obs)["alive"], jax.random.key(0))
    assert shape.shape == (2, cartpole.spec.max_episode_steps + 1)


def test_success_rate_needs_outcome_flags(cartpole):
    with pytest.raises(ValueError, match="arrived/crashed"):
        rollout.success_rate(cartpole, rollout.random_policy(4), jax.random.key(0), 2)


# ---- autoreset ------------------------------------------------------------------------------------------------
N = 10


@pytest.fixture(scope="module")
def batch(cartpole):
    env, params = cartpole, cartpole.default_params
    states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), N), params)
    stepped = jax.vmap(env.step, in_axes=(0, 0, None))(states, jnp.full(N, 3, jnp.int32), params)
    keys = jax.random.split(jax.random.key(1), N)
    return env, params, stepped, keys


def _leaves(tree):
    return [np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
            for x in jax.tree.leaves(tree)]


@pytest.mark.parametrize("n_done", [0, 2, 3, 7, N])
def test_autoreset_fresh_state_for_done_envs_only_whatever_the_capacity(batch, n_done):
    """Done envs take ``env.reset(keys[i])`` (each its own key: distinct fresh starts), the others are untouched,
    and the gathered path (capacity 3: exceeded by 7 and 10 done envs, so the fallback runs too) equals the
    select over the batch."""
    env, params, stepped, keys = batch
    done = jnp.zeros(N, bool).at[jnp.asarray([1, 4, 5, 8, 2, 9, 0, 3, 6, 7][:n_done], jnp.int32)].set(True)
    fresh = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    results = {cap: jax.jit(lambda d, cap=cap: autoreset.autoreset(env, d, keys, params, stepped, cap))(done)
               for cap in (None, 3, N)}
    mask = np.asarray(done)
    for cap, got in results.items():
        for g, f, s in zip(_leaves(got), _leaves(fresh), _leaves(stepped)):
            np.testing.assert_array_equal(g[~mask], s[~mask], err_msg=f"capacity {cap}: a running env changed")
            # The reset compiled inside another program may round differently in the last bit.
            np.testing.assert_allclose(g[mask], f[mask], rtol=1e-6, atol=1e-9, err_msg=f"capacity {cap}")
    for cap in (3, N):  # bit for bit the same whichever path resets
        for a, b in zip(_leaves(results[None]), _leaves(results[cap])):
            np.testing.assert_array_equal(a, b)
    if n_done >= 2:
        obs = np.asarray(results[3].obs)[np.asarray(done)]
        assert len({tuple(o) for o in obs}) == n_done  # fresh randomness: no two envs start alike
        assert np.all(np.asarray(results[3].steps)[np.asarray(done)] == 0)


def test_reset_where_gathers_only_the_done_envs_values(batch):
    """``reset(keys, envs)`` sees the gathered envs' own keys and indices, so derived values (the trainer's
    discretised states and table rows) follow their env."""
    _, _, _, keys = batch
    done = jnp.asarray([False, True, False, False, True, False, False, False, False, True])
    current = (jnp.full(N, -1, jnp.int32), jnp.zeros((N, 2), jnp.uint32))

    def reset(k, envs):
        index = jnp.arange(N, dtype=jnp.int32) if envs is None else envs
        return index * 100, jax.random.key_data(k)

    want_index = np.where(np.asarray(done), np.arange(N) * 100, -1)
    want_keys = np.where(np.asarray(done)[:, None], np.asarray(jax.random.key_data(keys)), 0)
    for capacity in (4, None):
        index, key_data = jax.jit(lambda d, c=capacity: autoreset.reset_where(reset, d, keys, current, c))(done)
        np.testing.assert_array_equal(np.asarray(index), want_index)
        np.testing.assert_array_equal(np.asarray(key_data), want_keys)


def test_where_done_single_env_form(cartpole):
    a = cartpole.reset(jax.random.key(0))
    b = cartpole.reset(jax.random.key(1))
    for done, want in ((jnp.bool_(True), a), (jnp.bool_(False), b)):
        for g, w in zip(_leaves(autoreset.where_done(done, a, b)), _leaves(want)):
            np.testing.assert_array_equal(g, w)
