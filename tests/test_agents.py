"""Learners: TD targets against rlax, the seed-compat mode against an independent dict-based reference."""
from __future__ import annotations

import random

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import rlax
from hypothesis import given, settings
from hypothesis import strategies as st

import agents
from jaxrobo.tabular import learner as tabular
from agents.qlearning import noisy_greedy
from jaxrobo.tabular.learner import AgentParams

N_S, N_A = 5, 4
PARAMS = AgentParams(alpha=0.3, gamma=0.9, epsilon=0.2)


def _random_agent(seed: int, n_tables: int = 1) -> tabular.AgentState:
    q = jax.random.normal(jax.random.key(seed), (n_tables, N_S, N_A))
    return tabular.AgentState(q, None)


def _td(name: str, agent, s, a, r, s2, a2, terminated, key=jax.random.key(0)):
    learner = agents.get(name)
    table, old, new = tabular.new_entry(learner, key, agent, s, a, jnp.float32(r), s2, a2, jnp.bool_(terminated),
                                        jnp.float32(PARAMS.epsilon), PARAMS)
    return int(table), float((new - old) / PARAMS.alpha)


transitions = st.tuples(st.integers(0, 10_000), st.integers(0, N_S - 1), st.integers(0, N_A - 1),
                        st.floats(-5, 5), st.integers(0, N_S - 1), st.integers(0, N_A - 1), st.booleans())


@settings(max_examples=15, deadline=None)
@given(transitions)
def test_td_errors_match_rlax(t):
    seed, s, a, r, s2, a2, term = t
    agent = _random_agent(seed)
    q = agent.q[0]
    disc = PARAMS.gamma * (1.0 - term)
    expected = {
        "qlearn": rlax.q_learning(q[s], a, r, disc, q[s2]),
        "sarsa": rlax.sarsa(q[s], a, r, disc, q[s2], a2),
        "expected_sarsa": rlax.expected_sarsa(q[s], a, r, disc, q[s2],
                                              tabular.epsilon_greedy_probabilities(q[s2], PARAMS.epsilon)),
    }
    for name, td in expected.items():
        assert _td(name, agent, s, a, r, s2, a2, term)[1] == pytest.approx(float(td), rel=1e-4, abs=1e-4), name


@settings(max_examples=10, deadline=None)
@given(transitions)
def test_double_q_matches_rlax_for_the_table_it_updates(t):
    seed, s, a, r, s2, a2, term = t
    agent = _random_agent(seed, n_tables=2)
    table, td = _td("double_q", agent, s, a, r, s2, a2, term, key=jax.random.key(seed))
    other = 1 - table
    q = agent.q
    expected = rlax.double_q_learning(q[table, s], a, r, PARAMS.gamma * (1.0 - term), q[other, s2], q[table, s2])
    assert td == pytest.approx(float(expected), rel=1e-4, abs=1e-4)


def test_double_q_updates_both_tables_over_time():
    learner = agents.get("double_q")
    agent = tabular.init(learner, N_S, N_A)
    for i in range(20):
        agent = tabular.learn(learner, jax.random.key(i), agent, 0, 1, jnp.float32(1.0), 1, 0, jnp.bool_(False),
                              jnp.float32(0.1), PARAMS)
    assert float(agent.q[0, 0, 1]) > 0 and float(agent.q[1, 0, 1]) > 0


# ---- seed compatibility ---------------------------------------------------------------------------------
class DictQLearn:
    """An independent re-statement of the seed's QLearn/Sarsa update rules (``seed_compat``), on a dict."""

    def __init__(self, alpha, gamma, on_policy):
        self.q, self.alpha, self.gamma, self.on_policy = {}, alpha, gamma, on_policy

    def learn(self, s, a, r, s2, a2):
        nxt = self.q.get((s2, a2), 0.0) if self.on_policy else max(self.q.get((s2, b), 0.0) for b in range(N_A))
        old = self.q.get((s, a))
        self.q[(s, a)] = r if old is None else old + self.alpha * (r + self.gamma * nxt - old)


@pytest.mark.parametrize("name", ["qlearn", "sarsa"])
def test_seed_compat_updates_match_a_dict_reference_on_a_tiny_mdp(name):
    learner = agents.get(name)
    ref = DictQLearn(PARAMS.alpha, PARAMS.gamma, learner.on_policy)
    agent = tabular.init(learner, N_S, N_A, seed_compat=True)
    update = jax.jit(lambda ag, s, a, r, s2, a2, term: tabular.learn(
        learner, jax.random.key(0), ag, s, a, r, s2, a2, term, jnp.float32(0.1), PARAMS, seed_compat=True))
    rng = random.Random(0)
    s = 0
    for _ in range(200):  # a random walk on a 5-state chain; reward at the right end, terminal there
        a = rng.randrange(N_A)
        s2 = min(N_S - 1, max(0, s + (1 if a % 2 else -1)))
        r = 1.0 if s2 == N_S - 1 else -0.1
        a2 = rng.randrange(N_A)
        ref.learn(s, a, r, s2, a2)
        agent = update(agent, s, a, jnp.float32(r), s2, a2, jnp.bool_(s2 == N_S - 1))  # terminal still bootstraps
        s = 0 if s2 == N_S - 1 else s2
    table = np.zeros((N_S, N_A))
    for (si, ai), v in ref.q.items():
        table[si, ai] = v
    np.testing.assert_allclose(np.asarray(agent.q[0]), table, rtol=1e-5, atol=1e-5)
    assert set(zip(*np.nonzero(np.asarray(agent.visited))))  == set(ref.q)


def test_textbook_mode_starts_at_zero_and_moves_by_alpha():
    learner = agents.get("qlearn")
    agent = tabular.init(learner, N_S, N_A)
    agent = tabular.learn(learner, jax.random.key(0), agent, 0, 0, jnp.float32(2.0), 1, 0, jnp.bool_(True),
                          jnp.float32(0.1), PARAMS)
    assert float(agent.q[0, 0, 0]) == pytest.approx(PARAMS.alpha * 2.0)


def test_seed_noise_exploration_matches_reference_frequencies():
    """With epsilon=1 the seed adds U[-mag/2, mag/2) noise to every value; compare the action frequencies."""
    q_row = jnp.array([1.0, 0.8, -0.5, 0.2])
    n = 20_000
    actions = jax.jit(jax.vmap(lambda k: noisy_greedy(k, q_row, jnp.float32(1.0))))(
        jax.random.split(jax.random.key(0), n))
    ours = np.bincount(np.asarray(actions), minlength=4) / n
    rng = np.random.default_rng(1)
    mag = 1.0
    noisy = np.asarray(q_row) + rng.random((n, 4)) * mag - 0.5 * mag
    ref = np.bincount(noisy.argmax(1), minlength=4) / n
    np.testing.assert_allclose(ours, ref, atol=0.02)


def test_greedy_breaks_ties_uniformly():
    q_row = jnp.array([1.0, 1.0, 0.0, 1.0])
    actions = jax.vmap(lambda k: tabular.greedy(k, q_row))(jax.random.split(jax.random.key(0), 3000))
    freq = np.bincount(np.asarray(actions), minlength=4) / 3000
    assert freq[2] == 0 and np.all(np.abs(freq[[0, 1, 3]] - 1 / 3) < 0.04)


def test_epsilon_greedy_explores_at_rate_epsilon():
    q_row = jnp.array([0.0, 5.0, 0.0, 0.0])
    actions = jax.vmap(lambda k: tabular.epsilon_greedy(k, q_row, jnp.float32(0.4)))(
        jax.random.split(jax.random.key(1), 5000))
    greedy_share = float(np.mean(np.asarray(actions) == 1))
    assert greedy_share == pytest.approx(0.6 + 0.4 / 4, abs=0.03)


def test_epsilon_schedule_follows_the_seed_rule():
    p = AgentParams(epsilon=0.1, epsilon_discount=0.999, epsilon_min=0.05)
    eps = tabular.epsilon_schedule(p, 1000)
    assert eps[0] == pytest.approx(0.0999)
    k = int(np.argmax(eps <= 0.05))  # the first value at or below the floor; it then stays there
    assert eps[k - 1] > 0.05 and np.all(eps[k:] == eps[k])
    np.testing.assert_allclose(np.asarray(tabular.decay_epsilon(jnp.float32(0.1), p)), 0.0999, rtol=1e-6)


def test_shared_table_averages_colliding_updates():
    learner = agents.get("qlearn")
    agent = tabular.init(learner, N_S, N_A)
    keys = jax.random.split(jax.random.key(0), 3)
    s = jnp.array([0, 0, 1]); a = jnp.array([2, 2, 0]); r = jnp.array([1.0, 3.0, 5.0])
    out = tabular.learn_shared(learner, keys, agent, s, a, r, jnp.array([4, 4, 4]), a, jnp.ones(3, bool),
                               jnp.full(3, 0.1), PARAMS)
    assert float(out.q[0, 0, 2]) == pytest.approx(PARAMS.alpha * 2.0)  # mean of 0.3*1 and 0.3*3
    assert float(out.q[0, 1, 0]) == pytest.approx(PARAMS.alpha * 5.0)


def test_unknown_agent_name_is_a_clear_error():
    with pytest.raises(ValueError, match="allowed values are qlearn, sarsa"):
        agents.get("dqn")


def test_rng_draws_equal_jax_random_under_jit_and_vmap():
    """jaxrobo.core.rng's unrolled threefry gives JAX's own numbers: results do not depend on which one ran."""
    from jaxrobo.core import rng

    for i in (0, 1, 7, 2**31 + 5):
        key = jax.random.key(i)
        for shape, low, high in (((6,), 0.0, 1.0), ((4,), -0.05, 0.05), ((), -3.14, 3.14), ((3, 5), 2.0, 7.5),
                                 ((0,), 0.0, 1.0)):
            ours = jax.jit(lambda k: rng.uniform(k, shape, low, high))(key)
            theirs = jax.jit(lambda k: jax.random.uniform(k, shape, jnp.float32, low, high))(key)
            np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))
            np.testing.assert_array_equal(np.asarray(jax.jit(lambda k: rng.bits(k, shape))(key)),
                                          np.asarray(jax.random.bits(key, shape, jnp.uint32)))
        for num in (1, 2, 5, 17):
            theirs = jax.random.key_data(jax.random.split(key, num))
            np.testing.assert_array_equal(np.asarray(jax.random.key_data(jax.jit(lambda k: rng.split(k, num))(key))),
                                          np.asarray(theirs))
            for j in range(num):
                np.testing.assert_array_equal(np.asarray(jax.random.key_data(rng.subkey(key, j, num))),
                                              np.asarray(theirs[j]))
        batch = jax.random.split(key, 7)
        ours = jax.jit(jax.vmap(lambda k: (jax.random.key_data(rng.split(k, 3)), rng.bernoulli(k, 0.3, (4,)))))(batch)
        theirs = jax.vmap(lambda k: (jax.random.key_data(jax.random.split(k, 3)), jax.random.bernoulli(k, 0.3, (4,))))(
            batch)
        for a, b in zip(ours, theirs):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="index must be in"):
        rng.subkey(jax.random.key(0), 3, 3)


def test_rng_traces_its_hash_once_per_shape_of_counters():
    """The draws call the hash jitted on its own: a program that draws twice at one shape holds one trace of it
    (the same jaxpr in both calls), one per shape; the plain hash a Pallas kernel calls stays inline ops."""
    from jaxrobo.core import rng

    def draws(key):
        k1, k2, k3 = rng.split(key, 3)
        return (rng.uniform(k1, (3,)), rng.uniform(k2, (3,)), rng.bits(k3, (5,)), rng.subkey(k1, 1, 4),
                rng.subkey(k2, 2, 4), rng.uniform_pair(k3))

    eqns = jax.make_jaxpr(draws)(jax.random.key(0)).jaxpr.eqns
    hashed = [e for e in eqns if e.primitive.name in ("pjit", "jit")]
    by_counters = {}
    for e in hashed:
        by_counters.setdefault(tuple(e.invars[3].aval.shape), []).append(e.params["jaxpr"])
    assert sorted(by_counters) == [(), (3,), (5,)], by_counters  # split's (3,) counters and two uniforms: one shape
    assert all(all(j is js[0] for j in js) for js in by_counters.values())
    assert [len(js) for _, js in sorted(by_counters.items())] == [3, 3, 1]
    words = [jnp.uint32(1), jnp.uint32(2), jnp.zeros(4, jnp.uint32), jnp.arange(4, dtype=jnp.uint32)]
    assert not [e for e in jax.make_jaxpr(rng.threefry2x32)(*words).jaxpr.eqns if e.primitive.name in ("pjit", "jit")]


def test_rng_defers_to_jax_random_for_other_key_implementations():
    from jaxrobo.core import rng

    key = jax.random.key(3, impl="rbg")
    np.testing.assert_array_equal(np.asarray(jax.random.key_data(rng.split(key, 3))),
                                  np.asarray(jax.random.key_data(jax.random.split(key, 3))))
    np.testing.assert_array_equal(np.asarray(rng.uniform(key, (5,))), np.asarray(jax.random.uniform(key, (5,))))
    u1, u2 = rng.uniform_pair(key)
    assert 0.0 <= float(u1) < 1.0 and 0.0 <= float(u2) < 1.0


SEEDS = [0, 1, 7, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**40 + 3, -1, -2**31, np.int64(5), np.uint32(9), np.int32(-4)]


@pytest.mark.parametrize("x64", [False, True])
def test_seed_key_is_jax_random_key(x64):
    from jaxrobo.core import rng

    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", x64)
    try:
        for seed in SEEDS:
            ours, theirs = rng.seed_key(seed), jax.random.key(seed)
            assert ours.dtype == theirs.dtype and ours.shape == theirs.shape and ours.sharding == theirs.sharding
            np.testing.assert_array_equal(np.asarray(jax.random.key_data(ours)),
                                          np.asarray(jax.random.key_data(theirs)), err_msg=f"seed {seed!r}")
    finally:
        jax.config.update("jax_enable_x64", before)


def test_seed_key_data_is_each_seeds_jax_key_data():
    from jaxrobo.core import rng

    def theirs(seeds):
        return np.stack([np.asarray(jax.random.key_data(jax.random.key(s))) for s in seeds])

    for seeds in ([0, 3, 2**32 - 1, np.int64(12)], [4, -1, 2**32 + 5]):  # host-written; one that defers
        ours = rng.seed_key_data(seeds)
        assert ours.dtype == np.uint32 and ours.shape == (len(seeds), 2)
        np.testing.assert_array_equal(ours, theirs(seeds))


def test_seed_key_runs_no_jax_seeding_where_the_key_is_known_and_defers_elsewhere(monkeypatch):
    from jaxrobo.core import rng

    asked = []
    real = jax.random.key
    monkeypatch.setattr(jax.random, "key", lambda seed, **kw: asked.append(seed) or real(seed, **kw))
    for seed in (0, 5, 2**32 - 1, np.int64(7)):
        rng.seed_key(seed)
    assert asked == []  # written on the host: no program compiled or run for these
    for seed in (-1, 2**32, True):
        rng.seed_key(seed)
    assert asked == [-1, 2**32, True]
    asked.clear()
    with jax.default_prng_impl("rbg"):  # another implementation's key data is its own: jax.random.key's
        np.testing.assert_array_equal(np.asarray(jax.random.key_data(rng.seed_key(3))),
                                      np.asarray(jax.random.key_data(real(3))))
    assert asked == [3]


@pytest.mark.parametrize("n", [1, 2, 4, 7, tabular.UNROLL_ACTIONS + 3])
def test_action_axis_reductions_match_numpy(n):
    rows = np.random.default_rng(n).integers(-3, 3, size=(50, n)).astype(np.float32)  # many ties
    np.testing.assert_array_equal(np.asarray(tabular.row_max(jnp.asarray(rows))), rows.max(-1))
    np.testing.assert_array_equal(np.asarray(tabular.row_min(jnp.asarray(rows))), rows.min(-1))
    np.testing.assert_array_equal(np.asarray(tabular.row_argmax(jnp.asarray(rows))), rows.argmax(-1))
    index = np.random.default_rng(n + 1).integers(0, n, size=50)
    np.testing.assert_array_equal(np.asarray(tabular.row_pick(jnp.asarray(rows), jnp.asarray(index))),
                                  rows[np.arange(50), index])


@pytest.mark.parametrize("n", [4, tabular.UNROLL_ACTIONS + 4])
def test_ties_are_picked_uniformly_by_one_draw(n):
    q_row = jnp.zeros(n).at[jnp.array([0, 2, n - 1])].set(1.0)
    u = jnp.arange(3000, dtype=jnp.float32) / 3000  # evenly spread draws: each tied action gets a third
    picks = np.asarray(jax.vmap(lambda x: tabular.pick_among_maxima(q_row, x))(u))
    np.testing.assert_array_equal(np.bincount(picks, minlength=n)[[0, 2, n - 1]], [1000, 1000, 1000])