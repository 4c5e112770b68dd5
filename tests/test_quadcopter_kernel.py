"""``ExecutionPlan.fused = "pallas"`` for the rigid quadcopter: its control step (controller + physics, every
substep) as one Pallas kernel (:mod:`envs.quadcopter.kernel`), run here interpreted on a CPU and held to the XLA
step as its oracle.

What is exact and what is not: the kernel and the XLA step run one source, the per-coordinate controller and
physics of :mod:`envs.quadcopter.dynamics`, and op by op they give the same bits. Compiled, XLA fuses the
kernel's program and the XLA step differently and contracts a multiply and an add that share a fusion into one
FMA (as it rounds the rolled and the written-out substep loops differently), so a compiled control step agrees to
float32 round-off; a training run's tables and records follow the plain path exactly until such a bit moves a
state across a bin edge, and for the tiny runs here none does.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.quadcopter.robot import Quadcopter
from envs.quadcopter.kernel import constants_of, control_step, make_advance
from jaxrobo.physics import fused
from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.training.run import resolve
from jaxrobo.physics.sim import JointState
from jaxrobo.training.trainer import Trainer

TINY = dict(n_envs=6, nepisodes=3, nsteps=20, chunk_steps=15, eval_episodes=2, eval_envs=2, backend="rigid")


@functools.lru_cache(maxsize=None)
def _robot(**kwargs) -> Quadcopter:
    return Quadcopter("rigid", **kwargs)


def _random_states(n: int, seed: int = 0) -> tuple[JointState, jax.Array]:
    """States over a wide envelope (tilted, spinning, moving) and commands over every Twist the tasks send."""
    k = jax.random.split(jax.random.key(seed), 5)
    pos = jax.random.uniform(k[0], (n, 3), minval=-3.0, maxval=3.0)
    quat = jax.random.normal(k[1], (n, 4))
    quat = quat / jnp.linalg.norm(quat, axis=1, keepdims=True)
    vel = jax.random.normal(k[2], (n, 3))
    omega = 2.0 * jax.random.normal(k[3], (n, 3))
    command = jax.random.uniform(k[4], (n, 4), minval=-1.5, maxval=1.5)
    return JointState(jnp.concatenate([pos, quat], 1), jnp.concatenate([vel, omega], 1)), command


def _under(choice: str, fn):
    def traced(*args):
        with fused.choose(choice):
            return fn(*args)

    return jax.jit(traced)


def _close(a: JointState, b: JointState) -> None:
    # Round-off of 30 substeps (FMA contraction, amplified by the spinning states): measured |kernel - XLA| /
    # (1 + |x|) <= 2e-7 (qpos) and 2.2e-6 (qvel) on a CPU, up to 7e-7 and 4e-6 before the dynamics were shared;
    # 1e-5 failed on an H100 (its libdevice sin/cos and contractions differ from XLA's), so the bound stays at the
    # 2e-5 that held there before.
    for name in ("qpos", "qvel"):
        np.testing.assert_allclose(np.asarray(getattr(b, name)), np.asarray(getattr(a, name)), rtol=2e-5, atol=2e-5,
                                   err_msg=name)


@pytest.mark.parametrize("kwargs", [{}, dict(running_step=0.05, min_altitude=0.5)])
def test_the_kernel_and_the_xla_step_are_one_set_of_equations(kwargs):
    """Op by op (no XLA fusion), the XLA control step (``Quadcopter.controller`` + ``RigidBodySim.physics_step``
    every substep, on stacked states) and the kernel's per-coordinate :func:`control_step` give the same bits:
    64 random states and commands, one control step (30 substeps; or 5 with the altitude floor on)."""
    robot = _robot(**kwargs)
    states, commands = _random_states(64, seed=3)
    with jax.disable_jit():
        xla = jax.vmap(robot.advance)(states, commands)
        q, v = control_step(constants_of(robot), [states.qpos[:, i] for i in range(7)],
                            [states.qvel[:, i] for i in range(6)], [commands[:, j] for j in range(4)])
    np.testing.assert_array_equal(np.stack(q, 1), np.asarray(xla.qpos))
    np.testing.assert_array_equal(np.stack(v, 1), np.asarray(xla.qvel))


@pytest.mark.parametrize("kwargs", [{}, dict(running_step=0.05, min_altitude=0.5)])
def test_the_kernel_agrees_with_the_xla_control_step(kwargs):
    """300 random states and commands (not a multiple of the block: the last program is masked), one control
    step (30 substeps; or 5 with the altitude floor on): the kernel's states are the XLA step's to round-off."""
    robot = _robot(**kwargs)
    states, commands = _random_states(300)
    xla = _under("off", jax.vmap(robot.advance))(states, commands)
    kernel = _under("pallas", jax.vmap(robot.advance))(states, commands)
    _close(xla, kernel)
    direct = jax.jit(make_advance(robot, block=64))(states, commands)  # another block size, same values
    for name in ("qpos", "qvel"):
        np.testing.assert_array_equal(np.asarray(getattr(direct, name)), np.asarray(getattr(kernel, name)))


def test_nested_vmaps_and_a_single_env_make_one_batch():
    """A vmap over configurations around the env batch (as a sweep runs it), with the commands batched or
    shared, and around a scan of steps, gives the flat batch's values, and the whole nest is one kernel call; an
    unbatched step agrees to round-off (a batch of one runs unvectorised here, which rounds a last bit
    differently)."""
    robot = _robot()
    states, commands = _random_states(12, seed=1)
    commands = jnp.tile(commands[:4], (3, 1))  # the same commands in each configuration
    flat = _under("pallas", jax.vmap(robot.advance))(states, commands)
    split = lambda x: x.reshape((3, 4) + x.shape[1:])  # noqa: E731
    nested_fn = jax.vmap(jax.vmap(robot.advance))
    nested = _under("pallas", nested_fn)(jax.tree.map(split, states), split(commands))
    shared = _under("pallas", jax.vmap(jax.vmap(robot.advance), in_axes=(0, None)))(
        jax.tree.map(split, states), commands[:4])
    one = _under("pallas", robot.advance)(jax.tree.map(lambda x: x[5], states), commands[5])
    for name in ("qpos", "qvel"):
        a = np.asarray(getattr(flat, name))
        np.testing.assert_array_equal(np.asarray(getattr(nested, name)).reshape(a.shape), a)
        np.testing.assert_array_equal(np.asarray(getattr(shared, name)).reshape(a.shape), a)
        np.testing.assert_allclose(np.asarray(getattr(one, name)), a[5], rtol=1e-6, atol=1e-6)
    with fused.choose("pallas"):
        program = str(jax.make_jaxpr(nested_fn)(jax.tree.map(split, states), split(commands)))
    assert program.count("pallas_call") == 1

    # A scan of batched steps, vmapped as a sweep vmaps a training chunk: the scan's body is batched as a jaxpr.
    def two_steps(s, c):
        return jax.lax.scan(lambda x, _: (jax.vmap(robot.advance)(x, c), None), s, None, length=2)[0]

    swept = _under("pallas", jax.vmap(two_steps))(jax.tree.map(split, states), split(commands))
    flat_twice = _under("pallas", two_steps)(states, commands)
    for name in ("qpos", "qvel"):
        a = np.asarray(getattr(flat_twice, name))
        np.testing.assert_array_equal(np.asarray(getattr(swept, name)).reshape(a.shape), a)


def test_a_non_finite_state_stays_non_finite_so_the_nan_guard_still_ends_the_episode():
    """A NaN in one env's state gives a non-finite state there (the env step's guard then ends the episode),
    and leaves the other envs' states as they would be."""
    robot = _robot()
    states, commands = _random_states(4, seed=2)
    bad = states.replace(qvel=states.qvel.at[1, 4].set(jnp.nan))
    xla = _under("off", jax.vmap(robot.advance))(bad, commands)
    kernel = _under("pallas", jax.vmap(robot.advance))(bad, commands)
    finite = lambda s: np.isfinite(np.asarray(s.qpos)).all(1) & np.isfinite(np.asarray(s.qvel)).all(1)  # noqa: E731
    np.testing.assert_array_equal(finite(kernel), [True, False, True, True])
    np.testing.assert_array_equal(finite(kernel), finite(xla))


def _goto(env_id: str = "QuadcopterGoto-v2", **overrides):
    return resolve(env_id, overrides={**TINY, **overrides})


def _plan(spec, **changes):
    return ExecutionPlan.for_run(spec.env, spec.config).replace(**changes)


def test_the_choice_is_accepted_for_the_rigid_quadcopter_with_any_learner_and_refused_elsewhere():
    for env_id, overrides in (("QuadcopterGoto-v2", {}), ("QuadcopterGoto-v1", dict(agent="sarsa")),
                              ("QuadcopterLiveShow-v0", dict(shared_table=True))):
        spec = _goto(env_id, **overrides)
        Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas"))  # accepted
    with pytest.raises(ValueError, match=r"fused='pallas': fused_block=64; .*leave fused_block None"):
        Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas", fused_block=64))
    spec = _goto(backend="mjx")
    with pytest.raises(ValueError, match=r"ExecutionPlan fused='pallas': .*backend='rigid'.*CartPoleStayUp"):
        Trainer(spec.env, spec.config, plan=_plan(spec, fused="pallas"))


def _carry(spec, n_chunks: int, **plan_changes):
    trainer = Trainer(spec.env, spec.config, plan=_plan(spec, **plan_changes))
    runner = jax.jit(trainer.init)(jax.random.key(5), spec.agent_params, spec.env.default_params)
    chunk = jax.jit(trainer.run_chunk)
    for _ in range(n_chunks):
        runner = chunk(runner, spec.agent_params, spec.env.default_params)
    as_data = lambda x: (  # noqa: E731
        jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
    return jax.tree_util.tree_flatten_with_path(jax.tree.map(as_data, runner))[0]


@pytest.mark.parametrize("overrides,kernel", [
    ({}, dict(fused="pallas")),  # the control step as the kernel, the task in XLA
    # the task's whole step as the kernel (envs/quadcopter/goto_kernel.py), with more obstacles than it writes
    # out and both kinds
    (dict(n_obstacles=3, obstacle_kind="mixed"), dict(fused="pallas", task_kernel=True)),
], ids=["control-step", "task-step"])
@pytest.mark.slow
def test_training_follows_the_plain_path_whatever_the_chunking(overrides, kernel):
    """Goto-v2, 4 envs feeding the preset's shared table, 45 training steps (episodes of at most 20): the
    kernel's run takes the plain path's actions, episodes and resets (every discrete part of the carry equal),
    its states, rewards, returns and table values equal to round-off (the reward reads continuous distances);
    and as 3 chunks of 15 or 5 chunks of 9 the kernel's carries are equal bit for bit."""
    plain = _carry(_goto(n_envs=4, **overrides), 3)
    kernel_run = _carry(_goto(n_envs=4, **overrides), 3, **kernel)
    rechunked = _carry(_goto(n_envs=4, chunk_steps=9, **overrides), 5, **kernel)
    for (path, a), (_, b), (_, c) in zip(plain, kernel_run, rechunked):
        name = jax.tree_util.keystr(path)
        a, b, c = np.asarray(a), np.asarray(b), np.asarray(c)
        np.testing.assert_array_equal(b, c, err_msg=name)
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-4, err_msg=name)
        else:
            np.testing.assert_array_equal(b, a, err_msg=name)
    episodes = dict((jax.tree_util.keystr(p), np.asarray(x)) for p, x in plain)[".episode"]
    assert episodes.sum() > 0  # episodes ended (and were reset) within the run


def test_it_lowers_for_the_gpu_through_triton(monkeypatch):
    """The kernel the GPU would run (not interpreted) lowers to a Triton call: atan2, asin, sin, cos, sqrt, the
    in-kernel substep loop and the masked word loads and stores all have Triton lowerings."""
    robot = _robot()
    states, commands = _random_states(1000)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    lowered = jax.jit(make_advance(robot)).trace(states, commands).lower(lowering_platforms=("cuda",))
    assert "__gpu$xla.gpu.triton" in lowered.as_text()
