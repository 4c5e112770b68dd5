"""``ExecutionPlan.fused = "pallas"``: the analytic cart-pole + Q-learning chunk as one Pallas kernel, run here in
interpret mode on CPU and held to the plain path as its oracle.

What is exact and what is not: the kernel draws JAX's own threefry numbers and writes the same step in the same order,
so keys, actions, table updates, resets, records and counters follow the plain path bit for bit. The physics is the
simulator's own equations, per coordinate in the kernel (``CartPoleSim.coordinate_step``) and on stacked coordinates in
the env's step; op by op they agree bit for bit (``tests/test_cartpole_physics.py``), but XLA fuses the two programs
differently and contracts a multiply and an add within a fusion into one FMA, so the continuous state is compared with a
tolerance. For these seeds no such difference moves a state across a bin edge, so the tables and records are equal; in a
long run one does, after which tabular learning takes another path (docs/benchmarks.md, "Pallas").
"""
from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxrobo.core.config import ConfigError
from envs.cartpole import kernel as cartpole_kernel
from jaxrobo.physics import libdevice_sincos
from jaxrobo.speed.plan import ExecutionPlan, chunk_kernel_refusal
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer
from jaxrobo.training.train import train
from test_randomise_kernels import CART_RANGES

TINY = dict(n_envs=12, nepisodes=4, nsteps=30, chunk_steps=25, eval_episodes=2, eval_envs=2,
            bins=[3, 6, 8, 10], state_low=[-2.4, -1.0, -0.3, -2.0], state_high=[2.4, 1.0, 0.3, 2.0])
FIELDS = ("q", "returns", "lengths", "terminated", "nan_episodes", "env_steps", "eval_returns", "eval_lengths")


def _cartpole(**overrides):
    return resolve("CartPoleStayUp-v0", overrides={**TINY, "backend": "analytic", **overrides})


def _plan(spec, **changes):
    return ExecutionPlan.for_run(spec.env, spec.config).replace(**changes)


def _leaves(runner):
    as_data = lambda x: (  # noqa: E731
        jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
    return jax.tree_util.tree_flatten_with_path(jax.tree.map(as_data, runner))[0]


def test_the_choice_is_validated_and_refused_where_it_does_not_apply():
    with pytest.raises(ValueError, match=r"fused='triton': allowed values are off, xla, pallas"):
        ExecutionPlan(fused="triton")
    assert repr(ExecutionPlan(fused="pallas")).endswith("fused=pallas, fused_block=all)")
    spec = _cartpole()
    Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas"))  # accepted
    for overrides, why in ((dict(agent="sarsa"), "agent='sarsa'"), (dict(shared_table=True), "shared_table=True"),
                           (dict(seed_compat=True), "seed_compat=True"), (dict(backend="mjx"), "backend='mjx'")):
        other = _cartpole(**overrides)
        with pytest.raises(ValueError, match=rf"ExecutionPlan fused='pallas': .*{why}"):
            Trainer(other.env, other.config, plan=_plan(other, fused="pallas"))
    with pytest.raises(ValueError, match=r"fused='pallas': fused_block=48; .* a power of two up to 1024"):
        Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas", fused_block=48))
    # rigid: tests/test_quadcopter_kernel.py
    goto = resolve("QuadcopterGoto-v1", overrides=dict(n_envs=4, backend="mjx"))
    with pytest.raises(ValueError, match=r"fused='pallas': the env is QuadcopterGoto"):
        Trainer(goto.env, goto.config, plan=_plan(goto, fused="pallas"))


def test_the_gpu_default_picks_the_kernel_where_it_applies(monkeypatch):
    """On one GPU from 16,384 envs the default plan runs the chunk as the kernel for every run it takes (by the
    rules that refuse an explicit choice), and keeps the plain path for the others; the quadcopter's default is its
    own (from 1,024 envs)."""
    def fused(spec, backend="gpu", **run):
        return ExecutionPlan.for_run(spec.env, spec.config, backend, **run).fused

    big = _cartpole(n_envs=16384)
    plan = ExecutionPlan.for_run(big.env, big.config, "gpu")
    assert (plan.fused, plan.fused_block, plan.reset_capacity) == ("pallas", None, 16384)
    assert "fused=pallas, fused_block=all" in repr(plan)  # printed, and part of the plan that keys the cache
    assert fused(_cartpole(n_envs=16384, discretiser="round", bins=None, resolution=0.5)) == "pallas"
    assert fused(big, "cpu") == "off" and fused(_cartpole(n_envs=16383)) == "off"
    assert fused(big, agent="sarsa") == "off"  # a Trainer's own learner, where it differs from the config's
    edges = dict(discretiser="edges", bins=None, state_low=None, state_high=None, edges=[[0.0], [0.0], [0.0], [0.0]])
    for overrides, why in ((dict(agent="sarsa"), "agent='sarsa'"), (dict(shared_table=True), "shared_table=True"),
                           (dict(seed_compat=True), "seed_compat=True"), (dict(backend="mjx"), "backend='mjx'"),
                           (dict(control_type="position"), "control_type='position'"), (edges, "discretiser='edges'")):
        other = _cartpole(n_envs=16384, **overrides)
        assert why in chunk_kernel_refusal(other.env, other.config)
        assert fused(other) == "off", overrides
        Trainer(other.env, other.config, plan=ExecutionPlan.for_run(other.env, other.config, "gpu"))  # accepted
    goto = resolve("QuadcopterGoto-v2", overrides=dict(n_envs=1024, backend="rigid"))
    assert (fused(goto), ExecutionPlan.for_run(goto.env, goto.config, "gpu").task_kernel) == ("pallas", True)
    # The config's `fused` (`--set fused=...`, a preset, a sweep) names the choice; "auto" leaves it to the plan.
    assert [fused(_cartpole(n_envs=16384, fused=f)) for f in ("off", "xla", "auto")] == ["off", "xla", "pallas"]
    assert fused(_cartpole(n_envs=12, fused="pallas"), "cpu") == "pallas"
    assert fused(resolve("QuadcopterGoto-v2", overrides=dict(n_envs=1024, backend="rigid", fused="off"))) == "off"
    with pytest.raises(ConfigError, match="ExecutionPlan fused='pallas': backend='mjx'"):
        mjx = _cartpole(n_envs=12, backend="mjx", fused="pallas")
        Trainer(mjx.env, mjx.config)
    # Two devices: the whole-chunk kernel runs on each device's envs; a run that takes the control-step kernel
    # (a custom call XLA cannot split) stays on one device unless `devices` is set, so the automatic plan is the
    # one-device plan; with devices=2 set, its step is written out instead.
    monkeypatch.setattr(jax, "device_count", lambda *a, **k: 2)
    split = ExecutionPlan.for_run(big.env, big.config, "gpu")
    assert (split.fused, split.devices) == ("pallas", 2)
    alone = ExecutionPlan.for_run(goto.env, goto.config, "gpu")
    assert (alone.fused, alone.devices, alone.task_kernel) == ("pallas", 1, True)
    two = resolve("QuadcopterGoto-v2", overrides=dict(n_envs=1024, backend="rigid", devices=2))
    assert (fused(two), ExecutionPlan.for_run(two.env, two.config, "gpu").devices) == ("xla", 2)


def test_training_gives_the_plain_path_tables_and_records():
    """12 envs (blocks of 4), 4 episodes of at most 30 steps, chunks of 25: tables, records and evaluation equal."""
    spec = _cartpole()
    plain = train(spec.env, spec.config, spec.agent_params, plan=_plan(spec))
    fused = train(spec.env, spec.config, spec.agent_params, plan=_plan(spec, fused="pallas"))
    assert fused.summary()["execution_plan"] == repr(_plan(spec, fused="pallas"))
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(plain, name)), np.asarray(getattr(fused, name)),
                                      err_msg=name)
    assert int(np.asarray(plain.lengths).min()) > 0  # every env recorded its episodes


def test_the_step_budget_follows_the_plain_path():
    """total_steps: every env steps 60 steps (chunks of 25: the last one part-useful), records capped at 4 episodes
    an env: tables, records and counters as the plain path's; total_episodes is refused by the kernel's rules."""
    spec = _cartpole(total_steps=12 * 60, nepisodes=4)
    plain = train(spec.env, spec.config, spec.agent_params, plan=_plan(spec))
    fused = train(spec.env, spec.config, spec.agent_params, plan=_plan(spec, fused="pallas"))
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(plain, name)), np.asarray(getattr(fused, name)),
                                      err_msg=name)
    assert plain.env_steps == 12 * 60 and plain.budget == "steps"
    runs = _cartpole(total_episodes=30)
    assert "total_episodes" in chunk_kernel_refusal(runs.env, runs.config)


@pytest.mark.slow
@pytest.mark.parametrize("changes", [dict(record_episodes=False, carry_rows=True), dict(chunk_steps=7)])
def test_the_carry_follows_the_plain_path_whatever_the_chunking(changes):
    """The whole carry after 75 steps (records off with carried rows) or 77 (chunks of 7): discrete parts bit for bit,
    the physics state within float tolerance; and the kernel's own result does not depend on the chunking."""
    carry_rows = changes.pop("carry_rows", False)
    spec = _cartpole(n_envs=6, **changes)
    steps = 75
    carries = {}
    for fused in ("off", "pallas"):
        trainer = Trainer(spec.env, spec.config, plan=_plan(spec, fused=fused, carry_rows=carry_rows))
        runner = jax.jit(trainer.init)(jax.random.key(3), spec.agent_params, spec.env.default_params)
        chunk = jax.jit(trainer.run_chunk)
        for _ in range(-(-steps // spec.config.chunk_steps)):
            runner = chunk(runner, spec.agent_params, spec.env.default_params)
        carries[fused] = runner
    assert (carries["off"].q_rows is None) != carry_rows
    for (path, a), (_, b) in zip(_leaves(carries["off"]), _leaves(carries["pallas"])):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, jax.tree_util.keystr(path)
        if jax.tree_util.keystr(path).split(".")[-1] in ("qpos", "qvel", "obs"):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6, err_msg=jax.tree_util.keystr(path))
        else:
            np.testing.assert_array_equal(a, b, err_msg=jax.tree_util.keystr(path))
    assert int(np.asarray(carries["off"].episode).sum()) > 0


def test_the_kernel_is_chunking_invariant():
    """75 steps as 3 chunks of 25 or 5 chunks of 15: the kernel's carries agree bit for bit."""
    out = {}
    for chunk_steps, n_chunks in ((25, 3), (15, 5)):
        spec = _cartpole(n_envs=4, chunk_steps=chunk_steps)
        trainer = Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas"))
        runner = jax.jit(trainer.init)(jax.random.key(5), spec.agent_params, spec.env.default_params)
        chunk = jax.jit(trainer.run_chunk)
        for _ in range(n_chunks):
            runner = chunk(runner, spec.agent_params, spec.env.default_params)
        out[chunk_steps] = runner
    for (path, a), (_, b) in zip(_leaves(out[25]), _leaves(out[15])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))


@pytest.mark.slow
@pytest.mark.parametrize("case", ["none", "all", "some"])
def test_the_reset_branch_changes_nothing(case):
    """A program hashes the reset's numbers only in a step where one of its envs is done: in a chunk where no env
    resets (3 steps of fresh episodes), where every env resets every step (nsteps=1) and where some do, the carry
    equals the unbranched kernel's (the reset computed in every env every step) bit for bit. 8 envs in programs
    of 4 (the plan's ``skip_resets`` on and off)."""
    overrides = {"none": dict(chunk_steps=3), "all": dict(nsteps=1, chunk_steps=3),
                 "some": dict(nsteps=200, chunk_steps=40)}
    spec = _cartpole(n_envs=8, **overrides[case])
    out = {}
    for skip in (True, False):
        trainer = Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas", fused_block=4, skip_resets=skip))
        runner = jax.jit(trainer.init)(jax.random.key(7), spec.agent_params, spec.env.default_params)
        out[skip] = jax.jit(trainer.run_chunk)(runner, spec.agent_params, spec.env.default_params)
    episodes, steps = np.asarray(out[True].episode), np.asarray(out[True].env_state.steps)
    assert {"none": episodes.max() == 0, "all": (episodes == 3).all(),  # "some": resets at different steps
            "some": episodes.max() > 0 and len(set(steps.tolist())) > 1}[case], (episodes, steps)
    for (path, a), (_, b) in zip(_leaves(out[True]), _leaves(out[False])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))


#: Domain randomisation's ranges (cart mass, pole mass, pole length, observation noise): those with which
#: tests/test_randomise_kernels.py holds the randomised kernel to the plain path.
RANDOMISED = dict(randomise=True, **CART_RANGES)


@pytest.mark.slow
@pytest.mark.parametrize("domain", [{}, RANDOMISED], ids=["nominal", "randomised"])
def test_groups_of_four_lanes_hash_the_resets_as_each_lane_would(domain):
    """Where at most a quarter of a program's envs are done, groups of four lanes share their reset's hashes
    (the plan's ``group_resets``); randomised, where at most an eighth are, groups of eight,
    the draws' hashes too; beyond that each lane hashes its own. 32 envs in programs of 16 over 80 steps, in which
    a program has one, two or three and more than four envs done in one step (counted on the plain path, step by
    step: both group sizes and the lanes' path run): the carry equals the lane-by-lane kernel's and the
    kernel's that hashes every reset in every env every step (randomised: its draws and its first observation's
    noise too), bit for bit."""
    spec = _cartpole(n_envs=32, nepisodes=40, nsteps=25, chunk_steps=80, **domain)
    # How many envs of each program of 16 are done in each step, on the plain path.
    one = _cartpole(n_envs=32, nepisodes=40, nsteps=25, chunk_steps=1, **domain)
    trainer = Trainer(one.env, one.config, plan=_plan(one, fused="off"))
    runner = jax.jit(trainer.init)(jax.random.key(3), one.agent_params, one.env.default_params)
    step = jax.jit(trainer.run_chunk)
    counts = set()
    for _ in range(80):
        before = np.asarray(runner.episode)
        runner = step(runner, one.agent_params, one.env.default_params)
        counts |= set((np.asarray(runner.episode) - before).reshape(2, 16).sum(1).tolist())
    assert {1, 2, 3} <= counts and max(counts) > 4, counts
    out = {}
    for group, skip in ((True, True), (False, True), (False, False)):
        plan = _plan(spec, fused="pallas", fused_block=16, group_resets=group, skip_resets=skip)
        trainer = Trainer(spec.env, spec.config, plan=plan)
        runner = jax.jit(trainer.init)(jax.random.key(3), spec.agent_params, spec.env.default_params)
        out[group, skip] = jax.jit(trainer.run_chunk)(runner, spec.agent_params, spec.env.default_params)
    assert np.asarray(out[True, True].episode).sum() > 60
    if domain:  # the draws moved through the groups: fresh episodes drew distinct pole lengths in range
        drawn = np.asarray(out[True, True].env_state.domain["pole_length"])
        assert ((drawn >= 0.5) & (drawn <= 2.0)).all() and len(np.unique(drawn)) > 16
    for other in set(out) - {(True, True)}:
        for (path, a), (_, b) in zip(_leaves(out[True, True]), _leaves(out[other])):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=f"{other} {jax.tree_util.keystr(path)}")


def test_the_kernels_erfinv_is_jaxs_bit_for_bit():
    """The kernel's noise evaluates ``erfinv`` with each branch's constants in the instructions
    (:func:`envs.cartpole.kernel._erf_inv`), for registers; its values are ``jax.lax.erf_inv``'s bit for bit,
    here under ``jit`` across the uniform draws' whole range and at its ends (on a GPU the same holds inside a Pallas
    kernel). If JAX changes its ``erf_inv``, this fails first."""
    import jax.numpy as jnp

    low = np.nextafter(np.float32(-1), np.float32(0))
    x = np.concatenate([np.linspace(low, 1, 400_000, endpoint=False, dtype=np.float32),
                        np.float32([low, -0.5, 0.0, 1e-30, 0.5, np.nextafter(np.float32(1), np.float32(0)), 1.0])])
    ours = np.asarray(jax.jit(cartpole_kernel._erf_inv)(jnp.asarray(x)))
    jaxs = np.asarray(jax.jit(jax.lax.erf_inv)(jnp.asarray(x)))
    np.testing.assert_array_equal(ours.view(np.int32), jaxs.view(np.int32))
    assert np.isinf(ours[-1]) and np.abs(ours[:-1]).max() > 3.5  # the tails were reached


@pytest.mark.parametrize("limit", [0.0, 0.05, 10.0])
def test_a_step_beyond_the_written_out_sin_cos_is_redone_with_the_calls(limit, monkeypatch):
    """Under the plan's ``fast_sincos`` a step whose pole angles all stay within the written-out sin/cos's range
    (:func:`jaxrobo.physics.libdevice_sincos.written_out`'s ``limit``) keeps their values, and a step where any
    leaves it is redone with ``jnp.sin``/``jnp.cos``. Interpreted, the written-out form is stood in for by one that
    is off by 0.01: with the range at 0 every step is redone (the carry is the calls' bit for bit), at 10 none is
    (the carry differs), at 0.05 some are and some are not (it differs too, and both forms ran: the carry is
    neither's)."""
    import jax.numpy as jnp

    spec = _cartpole(n_envs=8, nsteps=200, chunk_steps=40)

    def run(fast, limit=limit):
        monkeypatch.setattr(libdevice_sincos, "written_out", lambda: libdevice_sincos.WrittenOut(
            lambda t: (jnp.sin(t) + 0.01, jnp.cos(t)), limit))
        trainer = Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas", fused_block=4, fast_sincos=fast))
        runner = jax.jit(trainer.init)(jax.random.key(5), spec.agent_params, spec.env.default_params)
        return jax.jit(trainer.run_chunk)(runner, spec.agent_params, spec.env.default_params)

    calls, written = run(False), run(True)
    th = lambda r: np.asarray(r.env_state.pipeline_state.qpos[:, 1])  # noqa: E731
    if limit == 0.0:
        for (path, a), (_, b) in zip(_leaves(calls), _leaves(written)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=jax.tree_util.keystr(path))
    else:
        assert not np.array_equal(th(calls), th(written))
    if limit == 0.05:
        assert not np.array_equal(th(run(True, 10.0)), th(written))


def test_the_written_out_sin_cos_are_offered_only_where_verified(monkeypatch):
    """The trainer hands the kernel the written-out sin/cos only where :func:`jaxrobo.physics.libdevice_sincos.verified`
    (a GPU whose libdevice they match); a CPU has none."""
    assert libdevice_sincos.written_out() is None  # the tests' CPU
    monkeypatch.setattr(libdevice_sincos, "verified", lambda: True)
    assert libdevice_sincos.written_out() == (libdevice_sincos.sincos, libdevice_sincos.LIMIT)


def test_a_sweep_vmaps_the_kernel():
    """Two learning rates vmapped over the chunk (as a sweep runs it): the plain path's tables."""
    import jax.numpy as jnp

    spec = _cartpole(n_envs=4, chunk_steps=10)
    params = jax.tree.map(lambda x: jnp.asarray([x, x * 0.5], jnp.float32), spec.agent_params)
    tables = []
    for fused in ("off", "pallas"):
        trainer = Trainer(spec.env, spec.config, plan=_plan(spec, fused=fused))
        runner = jax.vmap(trainer.init, in_axes=(None, 0, None))(jax.random.key(0), params, spec.env.default_params)
        chunk = jax.jit(jax.vmap(trainer.run_chunk, in_axes=(0, 0, None)))
        for _ in range(3):
            runner = chunk(runner, params, spec.env.default_params)
        tables.append(np.asarray(runner.agent.q))
    np.testing.assert_array_equal(tables[0], tables[1])
    assert np.abs(tables[0]).sum() > 0


def test_it_lowers_for_the_gpu_through_triton(monkeypatch):
    """The kernel the GPU would run (not interpreted) lowers to a Triton call: the ops it uses (in-kernel loop,
    gathers and masked scatters by computed index, uint32 hashing, block-wide sums moving words between lanes,
    inline PTX fmas) all have Triton lowerings."""
    monkeypatch.setattr(libdevice_sincos, "verified", lambda: True)  # the written-out sin/cos (inline PTX) too
    spec = _cartpole(n_envs=512, record_episodes=True)
    trainer = Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas"))
    runner = jax.jit(trainer.init)(jax.random.key(0), spec.agent_params, spec.env.default_params)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    lowered = jax.jit(trainer.run_chunk).trace(runner, spec.agent_params, spec.env.default_params).lower(
        lowering_platforms=("cuda",))
    assert "__gpu$xla.gpu.triton" in lowered.as_text()


def test_a_subclass_that_changes_a_hook_gets_no_kernel():
    """The kernel holds the task's hooks' meaning: a subclass overriding one is refused by name (the plan's default
    then keeps the plain path), the continuous task offers none, and a plain subclass keeps it."""
    from envs.cartpole.continuous import CartPoleContinuous
    from envs.cartpole.stay_up import CartPoleStayUp

    spec = _cartpole()

    class Harder(CartPoleStayUp):
        def _is_done(self, obs, pipeline_state, task, params):
            return super()._is_done(obs, pipeline_state, task, params) | (obs[1] > 1.0)

    class Same(CartPoleStayUp):
        pass

    harder, same = Harder(spec.env.options), Same(spec.env.options)
    assert "Harder overrides _is_done" in chunk_kernel_refusal(harder, spec.config)
    assert chunk_kernel_refusal(same, spec.config) is None
    assert "offers no whole-chunk kernel" in chunk_kernel_refusal(CartPoleContinuous(), spec.config)
    with pytest.raises(ConfigError, match="ExecutionPlan fused='pallas': Harder overrides _is_done"):
        Trainer(harder, spec.config, plan=_plan(spec, fused="pallas"))
