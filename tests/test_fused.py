"""The fused path (``ExecutionPlan.fused``): validated and named in the plan, and held to the plain path as its
oracle: the same tables, records and evaluation bit for bit, whatever the block size and the chunking."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from jax.extend.core import jaxprs_in_params

from jaxrobo.training import driver
from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer

# The test_plan sizes (bins small, so the tables and compiles stay small).
from jaxrobo.training.train import train
TINY = dict(n_envs=12, nepisodes=4, nsteps=30, chunk_steps=25, eval_episodes=2, eval_envs=2,
            bins=[3, 6, 8, 10], state_low=[-2.4, -1.0, -0.3, -2.0], state_high=[2.4, 1.0, 0.3, 2.0])
FIELDS = ("q", "returns", "lengths", "terminated", "nan_episodes", "env_steps", "eval_returns", "eval_lengths")


def _cartpole(**overrides):
    return resolve("CartPoleStayUp-v0", overrides={**TINY, "backend": "analytic", **overrides})


def _same(a, b):
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)


def test_the_choice_is_validated_and_named():
    with pytest.raises(ValueError, match=r"fused='triton': allowed values are off, xla, pallas"):
        ExecutionPlan(fused="triton")
    with pytest.raises(ValueError, match=r"fused_block=0: expected None or an integer >= 1"):
        ExecutionPlan(fused="xla", fused_block=0)
    plan = ExecutionPlan(fused="xla", fused_block=5)
    assert repr(plan).endswith("carry_rows=off, fused=xla, fused_block=5)")
    assert repr(ExecutionPlan(fused="xla")).endswith("fused=xla, fused_block=all)")
    assert "fused" not in repr(ExecutionPlan())  # off: the plan reads as before the choice existed
    assert plan.to_dict()["fused"] == "xla" and plan.to_dict()["fused_block"] == 5
    assert plan != plan.replace(fused="off")  # another plan, another program (and cache key)


def test_the_plan_fuses_where_it_measured_faster():
    """Training 1,024 envs or more on a GPU, a closed form with more than 8 substeps (the quadcopter's 30) runs
    fused; fewer envs, a CPU, the cart-pole's 4 substeps (written out either way; with Q-learning its whole chunk
    is the Pallas kernel instead, tests/test_fused_pallas.py), MJX and envs stepped outside training do not; no
    plan blocks envs by default."""
    goto = resolve("QuadcopterGoto-v1", overrides=dict(n_envs=1024))
    assert ExecutionPlan.for_run(goto.env, goto.config, "gpu").fused == "pallas"  # its robot has a kernel
    mjx = resolve("QuadcopterGoto-v1", overrides=dict(n_envs=1024, backend="mjx"))
    assert ExecutionPlan.for_run(mjx.env, mjx.config, "gpu").fused == "off"
    assert ExecutionPlan.for_run(goto.env, goto.config, "gpu").fused_block is None
    assert ExecutionPlan.for_run(goto.env, goto.config, "cpu").fused == "off"
    assert ExecutionPlan.for_run(goto.env, backend="gpu").fused == "off"
    small = resolve("QuadcopterGoto-v1", overrides=dict(n_envs=1023))
    assert ExecutionPlan.for_run(small.env, small.config, "gpu").fused == "off"
    for cartpole in (_cartpole(n_envs=4096, agent="sarsa"), _cartpole(backend="mjx", n_envs=4096)):
        assert ExecutionPlan.for_run(cartpole.env, cartpole.config, "gpu").fused == "off"


@pytest.mark.slow
def test_blocks_of_envs_give_the_plain_values_whatever_the_chunking():
    """12 envs in blocks of 5 (5, 5, then 2), chunks of 25 and of 7 steps: the plain run's values bit for bit."""
    spec = _cartpole()
    plain_plan = ExecutionPlan.for_run(spec.env, spec.config)
    plain = train(spec.env, spec.config, spec.agent_params, plan=plain_plan)
    fused_plan = plain_plan.replace(fused="xla", fused_block=5)
    fused = train(spec.env, spec.config, spec.agent_params, plan=fused_plan)
    assert fused.summary()["execution_plan"] == repr(fused_plan)
    _same(plain, fused)
    rechunked = _cartpole(chunk_steps=7)
    _same(plain, train(rechunked.env, rechunked.config, rechunked.agent_params, plan=fused_plan))
    assert int(np.asarray(plain.lengths).min()) > 0  # every env recorded its episodes


@pytest.mark.slow
def test_on_policy_learner_and_shared_table_keep_their_values():
    """Sarsa (its carried next action crosses the block's steps) blocked (two blocks of 3: one body to compile);
    a shared table, which mixes every env each step, runs unblocked under the same plan."""
    for overrides in (dict(agent="sarsa", n_envs=6), dict(shared_table=True, n_envs=6)):
        spec = _cartpole(**overrides)
        plan = ExecutionPlan.for_run(spec.env, spec.config)
        _same(train(spec.env, spec.config, spec.agent_params, plan=plan),
              train(spec.env, spec.config, spec.agent_params, plan=plan.replace(fused="xla", fused_block=3)))


def _scans(fn, *args):
    """``(length, unroll)`` of the scans in ``fn``'s jaxpr, nested ones included."""
    out = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "scan":
                length, unroll = eqn.params["length"], eqn.params["unroll"]
                out.append((length, length if unroll is True else unroll))
            for sub in jaxprs_in_params(eqn.params):
                walk(sub)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return out


@pytest.mark.slow
def test_a_closed_form_writes_out_all_its_substeps_and_keeps_its_values():
    """The quadcopter's 30 rigid-body substeps per control step: a rolled loop in the plain path, written out in
    the fused one (one kernel); the chunk's tables and records are the same bit for bit."""
    spec = resolve("QuadcopterGoto-v1", overrides=dict(n_envs=4, nepisodes=2, nsteps=6, chunk_steps=5))
    env, ap, ep = spec.env, spec.agent_params, spec.env.default_params
    sim = env.robot.sim
    assert sim.cheap_step and sim.n_substeps == 30
    plain_plan = ExecutionPlan.for_run(env, spec.config)
    fused_plan = plain_plan.replace(fused="xla", fused_block=3)
    state = env.reset(jax.random.key(0), ep)
    step = lambda s: env.step(s, 0, ep)  # noqa: E731
    assert (30, 1) in _scans(plain_plan.traced(step), state)
    assert (30, 30) in _scans(fused_plan.traced(step), state)

    carries = []
    for plan in (plain_plan, fused_plan):
        trainer = Trainer(env, spec.config, plan=plan)
        runner = trainer.init(jax.random.key(1), ap, ep)
        chunk = driver.compiled_chunk(trainer, runner, ap, ep)
        carries.append(chunk(chunk(runner, ap, ep), ap, ep))
    plain = lambda x: jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x  # noqa: E731
    for a, b in zip(jax.tree.leaves(carries[0]), jax.tree.leaves(carries[1])):
        np.testing.assert_array_equal(np.asarray(plain(a)), np.asarray(plain(b)))
    assert int(np.asarray(carries[0].env_steps).min()) == 10
