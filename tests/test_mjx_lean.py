"""The MJX stage replacement (jaxrobo.physics.mjx_lean): bit for bit MJX as it is, scoped to its block,
version-guarded."""
from __future__ import annotations

import threading
import warnings

import jax
import mujoco
import numpy as np
import pytest

from jaxrobo.physics import mjx_lean
from envs import asset_path
from jaxrobo.physics.sim import load_model, mjx


@pytest.mark.parametrize("xml", ["cartpole.xml", "quadcopter.xml"])
def test_lean_steps_bit_for_bit_like_mjx_and_only_inside_its_block(xml):
    """``lean()`` (MJX's com_pos with cinert's upper triangle by static indices) gives what ``mjx.step`` gives,
    bit for bit, body inertias included, on random states of both robots; outside the block, disabled, and
    nested, MJX's own ``com_pos`` is what runs (one swap only)."""
    assert mjx_lean.unavailable() is None, mjx_lean.unavailable()  # the installed MJX is the one it was written for
    model = load_model(asset_path(xml), physics_only=True)
    m, d0 = mjx.put_model(model), mjx.put_data(model, mujoco.MjData(model))
    n = 16
    qpos = d0.qpos + 0.3 * jax.random.normal(jax.random.key(1), (n, model.nq))
    qvel = jax.random.normal(jax.random.key(2), (n, model.nv))
    ctrl = jax.random.normal(jax.random.key(3), (n, model.nu))

    def run(q, v, c):
        d = d0.replace(qpos=q, qvel=v, ctrl=c)
        # 10 steps in a loop: one step to compile, not ten unrolled (the swap is traced either way); the body
        # inertias are the last step's, as its com_pos left them.
        d = jax.lax.fori_loop(0, 10, lambda _, d: mjx.step(m, d), d)
        return d.qpos, d.qvel, d._impl.cinert

    stock = jax.jit(jax.vmap(run))(qpos, qvel, ctrl)
    original = mjx_lean._mjx_smooth.com_pos

    def lean_run(*args):
        with mjx_lean.lean():
            assert mjx_lean._mjx_smooth.com_pos is not original
            with mjx_lean.lean():  # nested: one swap only
                assert mjx_lean._mjx_smooth.com_pos.func is mjx_lean._com_pos_static_triu
                assert mjx_lean._mjx_smooth.com_pos.args == (original,)
            assert mjx_lean._mjx_smooth.com_pos is not original  # the inner block left the outer swap alone
            return run(*args)

    lean = jax.jit(jax.vmap(lean_run))(qpos, qvel, ctrl)
    assert mjx_lean._mjx_smooth.com_pos is original
    assert np.abs(np.asarray(stock[2])).max() > 0.0
    for a, b, name in zip(stock, lean, ("qpos", "qvel", "cinert")):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a), name)

    with mjx_lean.lean(False):
        assert mjx_lean._mjx_smooth.com_pos is original
    with pytest.raises(RuntimeError, match="inside"):
        with mjx_lean.lean():
            raise RuntimeError("inside")
    assert mjx_lean._mjx_smooth.com_pos is original  # restored after an error too


def test_choose_sets_what_the_simulator_asks_for_per_block_and_thread():
    assert mjx_lean.wanted() is True  # the default: lean
    seen = []
    with mjx_lean.choose(False):
        assert mjx_lean.wanted() is False
        with mjx_lean.choose(True):
            assert mjx_lean.wanted() is True
        assert mjx_lean.wanted() is False
        thread = threading.Thread(target=lambda: seen.append(mjx_lean.wanted()))
        thread.start()
        thread.join()
    assert mjx_lean.wanted() is True and seen == [True]  # another thread starts from the default


def test_the_simulator_traces_mjx_under_the_choice(mjx_step_spy):
    """``Simulator.physics_step`` swaps the stage exactly when the block being traced wants it."""
    from envs.cartpole.robot import CartPoleRobot

    sim = CartPoleRobot("velocity", "mjx").sim
    swapped = mjx_step_spy
    state = sim.init(jax.numpy.zeros(2), jax.numpy.zeros(2))
    ctrl = jax.numpy.zeros(1)
    jax.eval_shape(sim.physics_step, state, ctrl)
    with mjx_lean.choose(False):
        jax.eval_shape(sim.physics_step, state, ctrl)
    assert swapped == [True, False]


def test_the_simulator_traces_mjx_once_per_choice_whatever_programs_step_it(mjx_step_spy):
    """``MjxSim.physics_step`` is jitted on its own: MJX's Python is traced once per lean choice however many
    programs (and batch shapes) step the simulator, with the numbers of the step traced inline; the simulator
    still pickles after use, and the trace-reuse key does not see whether it was used."""
    import copy
    import pickle

    import jax.numpy as jnp

    from envs.cartpole.robot import CartPoleRobot
    from jaxrobo.speed import reuse

    sim = CartPoleRobot("velocity", "mjx").sim
    described = reuse.describe(sim)
    n = 5
    qpos = 0.3 * jax.random.normal(jax.random.key(1), (n, 2))
    qvel = jax.random.normal(jax.random.key(2), (n, 2))
    states = jax.vmap(sim.init)(qpos, qvel)
    ctrl = jax.random.normal(jax.random.key(3), (n, 1))
    stepped = jax.jit(jax.vmap(sim.physics_step))(states, ctrl)
    jax.eval_shape(jax.vmap(jax.vmap(sim.physics_step)), *jax.tree.map(lambda x: x[None], (states, ctrl)))
    jax.eval_shape(sim.physics_step, jax.tree.map(lambda x: x[0], states), ctrl[0])
    with mjx_lean.choose(False):
        jax.eval_shape(jax.vmap(sim.physics_step), states, ctrl)
    assert mjx_step_spy == [True, False]
    inline = jax.jit(jax.vmap(lambda s, c: sim._mjx_step(True, s, c, None)))(states, ctrl)
    for a, b in zip(jax.tree.leaves(stepped), jax.tree.leaves(inline)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert reuse.describe(sim) == described
    for again in (pickle.loads(pickle.dumps(sim)), copy.deepcopy(sim)):
        out = jax.jit(jax.vmap(again.physics_step))(states, ctrl)
        for a, b in zip(jax.tree.leaves(stepped), jax.tree.leaves(out)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("version,ok", [("3.17.0", True), ("3.17.5rc1", True), ("3.16.9", False), ("3.18.0", False),
                                        ("4.0.0", False), ("dev", False), (None, False)])
def test_outside_the_versions_it_was_written_for_it_is_a_no_op_that_says_why_once(monkeypatch, version, ok):
    monkeypatch.setattr(mjx_lean, "installed_version", lambda: version)
    monkeypatch.setattr(mjx_lean, "_WARNED", set())
    original = mjx_lean._mjx_smooth.com_pos
    reason = mjx_lean.unavailable()
    assert (reason is None) == ok
    if ok:
        return
    assert ("mujoco-mjx" in reason) and (version is None or version in reason)
    for _ in range(2):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with mjx_lean.lean():
                assert mjx_lean._mjx_smooth.com_pos is original
        messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
        if _ == 0:
            assert len(messages) == 1 and reason in messages[0]
        else:
            assert messages == []  # said once


def test_another_layout_is_a_no_op(monkeypatch):
    monkeypatch.setattr(mjx_lean, "_mjx_smooth", None)
    monkeypatch.setattr(mjx_lean, "_WARNED", set())
    assert "internals" in mjx_lean.unavailable()
    with pytest.warns(RuntimeWarning, match="internals"):
        with mjx_lean.lean():
            pass
