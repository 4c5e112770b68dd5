"""Discretiser: indices in range, clipping, the seed's round-to-0.1 mode, explicit edges, bad input."""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxrobo.tabular.discretise import make_discretiser

LOW, HIGH = [-2.5, -2.0, -0.7, -3.0], [2.5, 2.0, 0.7, 3.0]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-100, 100), min_size=4, max_size=4), st.integers(1, 12))
def test_bins_index_is_in_range_and_clips(obs, splits):
    d = make_discretiser(LOW, HIGH, number_splits=splits)
    idx = d.bin_indices(jnp.asarray(obs))
    assert np.all((np.asarray(idx) >= 0) & (np.asarray(idx) < splits))
    assert 0 <= int(d(jnp.asarray(obs))) < d.n_states == splits ** 4
    scaled = (np.asarray(obs, np.float64) - LOW) / (np.subtract(HIGH, LOW) / splits)
    expected = np.clip(np.floor(scaled), 0, splits - 1).astype(int)
    clear = np.abs(scaled - np.round(scaled)) > 1e-4  # float32 may land either side of an exact bin edge
    np.testing.assert_array_equal(np.asarray(idx)[clear], expected[clear])


def test_bins_are_a_bijection_on_bin_centres():
    d = make_discretiser(LOW, HIGH, number_splits=[2, 3, 4, 5])
    centres = [np.asarray(LOW[i]) + (np.arange(n) + 0.5) * (HIGH[i] - LOW[i]) / n for i, n in enumerate([2, 3, 4, 5])]
    pts = jnp.asarray(list(itertools.product(*centres)), jnp.float32)
    idx = np.asarray(jax.vmap(d)(pts))
    assert sorted(idx.tolist()) == list(range(d.n_states))


def test_round_mode_gives_each_tenth_its_own_state_like_the_seed():
    d = make_discretiser(LOW, HIGH, mode="round", resolution=0.1)
    assert d.bins == (51, 41, 15, 61)
    grid = np.round(np.arange(-0.7, 0.71, 0.1), 1)
    obs = jnp.asarray([[0.0, 0.0, g, 0.0] for g in grid], jnp.float32)
    idx = np.asarray(jax.vmap(d.bin_indices)(obs))[:, 2]
    np.testing.assert_array_equal(idx, np.arange(15))
    # values that round to the same tenth share a state, as the seed's string keys did
    assert int(d(jnp.array([0.04, 0.0, 0.0, 0.0]))) == int(d(jnp.array([-0.04, 0.0, 0.0, 0.0])))
    assert int(d(jnp.array([0.06, 0.0, 0.0, 0.0]))) != int(d(jnp.array([0.04, 0.0, 0.0, 0.0])))


def test_edges_mode_uses_the_given_cut_points():
    d = make_discretiser([-1, -1], [1, 1], mode="edges", edges=[[-0.1, 0.1], [0.0]])
    assert d.bins == (3, 2)
    assert np.asarray(d.bin_indices(jnp.array([-0.5, 0.5]))).tolist() == [0, 1]
    assert np.asarray(d.bin_indices(jnp.array([0.0, -0.5]))).tolist() == [1, 0]
    assert np.asarray(d.bin_indices(jnp.array([0.5, 0.0]))).tolist() == [2, 1]


@pytest.mark.parametrize("kwargs,fragment", [
    (dict(low=[0, 0], high=[1], number_splits=3), "equal-length"),
    (dict(low=[0, 1], high=[1, 0], number_splits=3), "high > low"),
    (dict(low=[0, 0], high=[1, 1], number_splits=0), "number_splits=0"),
    (dict(low=[0, 0], high=[1, 1], mode="hash"), "allowed values are bins, round, edges"),
    (dict(low=[0, 0], high=[1, 1], mode="edges", edges=[[0.5]]), "one list of edges per dimension"),
])
def test_bad_discretiser_settings_are_named(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment.replace("(", r"\(")):
        make_discretiser(**kwargs)
