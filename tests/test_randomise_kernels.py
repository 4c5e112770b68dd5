"""Domain randomisation inside the Pallas kernels (interpreted on a CPU), held to the randomised XLA path.

The kernels take each env's drawn domain (:mod:`jaxrobo.task.randomise`) as per-env inputs: the Goto task kernel
and the quadcopter's control-step kernel read the physics the XLA step reads (``Quadcopter.sim_physics``) and
leave the observation noise to the code around them; the cart-pole's chunk kernel, which resets in-kernel, draws
the domain and the noise from the XLA path's own keys. What is exact and what is not is as for the nominal
kernels (tests/test_fused_pallas.py, tests/test_quadcopter_goto_kernel.py): keys, draws, tables and records bit for
bit, the continuous state to float32 round-off (XLA fuses the kernel's program and the env's step differently).
With randomisation off the kernels are the programs they were (``scripts/fingerprints.py --check``).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrobo
from jaxrobo.physics import fused
from jaxrobo.speed.plan import ExecutionPlan, chunk_kernel_refusal, default_fused, physics_kernel, task_kernel
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import TrainConfig, Trainer

GOTO = "QuadcopterGoto-v2"
#: Ranges that change the physics well beyond round-off.
GOTO_RANGES = dict(rand_mass=[0.8, 1.2], rand_motor_gain=[0.9, 1.1], rand_wind=[0.0, 0.8], rand_obs_noise=[0.0, 0.05])
CART_RANGES = dict(rand_cart_mass=[0.5, 2.0], rand_pole_mass=[0.5, 2.0], rand_pole_length=[0.5, 2.0],
                   rand_obs_noise=[0.0, 0.05])
TINY = dict(n_envs=6, nepisodes=4, nsteps=30, chunk_steps=25, eval_episodes=2, eval_envs=2,
            bins=[3, 6, 8, 10], state_low=[-2.4, -1.0, -0.3, -2.0], state_high=[2.4, 1.0, 0.3, 2.0])


def _data(x):
    return jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x


def _leaves(tree):
    return jax.tree_util.tree_flatten_with_path(jax.tree.map(_data, tree))[0]


# ---- the Goto task kernel and the quadcopter's control-step kernel ---------------------------------------------
@functools.lru_cache(maxsize=None)
def _goto_steps(choice: str, task: bool, ranges: tuple = tuple(GOTO_RANGES.items()), n: int = 37, steps: int = 3):
    """``steps`` steps of ``n`` randomised envs from their resets, under ``fused.choose(choice, task)``."""
    env = jaxrobo.make(GOTO, randomise=True, **dict(ranges)) if ranges is not None else jaxrobo.make(GOTO)
    p = env.default_params
    states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), n), p)
    actions = jax.random.randint(jax.random.key(1), (steps, n), 0, 5)

    def run(s, actions):
        with fused.choose(choice, task):
            for a in actions:
                s = jax.vmap(env.step, in_axes=(0, 0, None))(s, a, p)
            return s

    with fused.choose(choice, task):
        program = str(jax.make_jaxpr(jax.vmap(env.step, in_axes=(0, 0, None)))(states, actions[0], p))
    return jax.jit(run)(states, actions), program.count("pallas_call")


@pytest.mark.slow
@pytest.mark.parametrize("task", [True, False], ids=["task-kernel", "control-step-kernel"])
def test_the_goto_kernels_fly_the_randomised_xla_flights(task):
    """37 envs (not a multiple of the block), each with its own mass, motor gain, wind and noise, 3 steps: the
    kernel (one call a step) gives the XLA step's states, observations (noise included) and outcomes to float32
    round-off, the drawn domain bit for bit; and the draws matter (the nominal flights differ)."""
    ref, calls_ref = _goto_steps("off", False)
    got, calls = _goto_steps("pallas", task)
    assert (calls_ref, calls) == (0, 1)
    for (path, a), (_, b) in zip(_leaves(ref), _leaves(got)):
        a, b, name = np.asarray(a), np.asarray(b), jax.tree_util.keystr(path)
        if name == ".obs":
            # A level sonar ray that grazes a cylinder has a range whose derivative in the heading is unbounded at
            # tangency: the last-ulp difference of Triton's and XLA's sin/cos on a GPU moved three of 296 readings
            # by up to 3 mm on an H100 (the discretiser's sonar bins are 0.5-1 m wide). The sonars are held to 1 cm,
            # the goal's terms to round-off.
            sonars = slice(3, 7)
            np.testing.assert_allclose(b[:, sonars], a[:, sonars], rtol=0, atol=1e-2, err_msg=name + " sonars")
            b, a = np.delete(b, np.s_[3:7], axis=1), np.delete(a, np.s_[3:7], axis=1)
        if np.issubdtype(a.dtype, np.floating) and "domain" not in name:
            np.testing.assert_allclose(b, a, rtol=2e-5, atol=5e-5, err_msg=name)
        else:
            np.testing.assert_array_equal(b, a, err_msg=jax.tree_util.keystr(path))
    nominal, _ = _goto_steps("pallas", task, None)
    assert np.abs(np.asarray(nominal.pipeline_state.qpos) - np.asarray(got.pipeline_state.qpos)).max() > 1e-3
    assert np.asarray(got.domain["wind"]).std() > 0.05


def test_a_randomised_control_step_at_nominal_values_is_the_nominal_one_op_by_op():
    """The kernels' per-coordinate control step given each env's domain at the nominal values (factors 1, no
    wind) gives the nominal step's bits, operation by operation (no XLA fusion); compiled, the two programs round
    a last bit differently (XLA contracts and folds constants differently when the factors are inputs), which
    the zero-width test below bounds."""
    from envs.quadcopter.kernel import constants_of, control_step
    from envs.quadcopter.robot import Quadcopter

    robot = Quadcopter("rigid")
    k = jax.random.split(jax.random.key(2), 3)
    q = list(jax.random.normal(k[0], (7, 32)))
    v = list(jax.random.normal(k[1], (6, 32)))
    cmd = list(jax.random.uniform(k[2], (4, 32), minval=-1.0, maxval=1.0))
    one, zero = jnp.ones(32), jnp.zeros(32)
    physics = robot.sim_physics({"mass": one, "motor_gain": one, "wind": zero, "wind_heading": zero})
    physics = {**physics, "wind": [physics["wind"][i] for i in range(3)]}  # per coordinate, as the kernel holds it
    with jax.disable_jit():
        nominal = control_step(constants_of(robot), q, v, cmd)
        drawn = control_step(constants_of(robot), q, v, cmd, physics)
    for a, b in zip(nominal[0] + nominal[1], drawn[0] + drawn[1]):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a))


@pytest.mark.slow
@pytest.mark.parametrize("task", [True, False], ids=["task-kernel", "control-step-kernel"])
def test_zero_width_ranges_fly_the_nominal_kernel(task):
    """randomise=true with every range pinned at its nominal value (the defaults) flies the nominal kernel's
    flights: the outcomes bit for bit, the states to float32 round-off (see the op-by-op test above)."""
    nominal, _ = _goto_steps("pallas", task, None)
    pinned, _ = _goto_steps("pallas", task, ())
    for (path, a), (_, b) in zip(_leaves(nominal.replace(domain=())), _leaves(pinned.replace(domain=()))):
        a, b = np.asarray(a), np.asarray(b)
        if np.issubdtype(a.dtype, np.floating):
            # The tolerance of the kernel-vs-XLA tests: the reward's progress term is a difference of distances.
            np.testing.assert_allclose(b, a, rtol=2e-5, atol=5e-5, err_msg=jax.tree_util.keystr(path))
        else:
            np.testing.assert_array_equal(b, a, err_msg=jax.tree_util.keystr(path))


def test_the_goto_kernel_with_randomisation_lowers_for_the_gpu(monkeypatch):
    env = jaxrobo.make(GOTO, randomise=True, **GOTO_RANGES)
    p = env.default_params
    st = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 8), p)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    from envs.quadcopter.goto_kernel import kernel_step

    text = jax.jit(jax.vmap(lambda s, a: kernel_step(env, s, a, p))).trace(st, jnp.zeros(8, jnp.int32)).lower(
        lowering_platforms=("cuda",)).as_text()
    assert text.count("__gpu$xla.gpu.triton") == 1


# ---- the cart-pole's chunk kernel ----------------------------------------------------------------------------
def _cartpole(**overrides):
    return resolve("CartPoleStayUp-v0", overrides={**TINY, "backend": "analytic", **overrides})


def _carry(spec, fused_choice: str, steps: int = 75, seed: int = 3):
    trainer = Trainer(spec.env, spec.config, plan=ExecutionPlan.for_run(spec.env, spec.config).replace(
        fused=fused_choice))
    runner = jax.jit(trainer.init)(jax.random.key(seed), spec.agent_params, spec.env.default_params)
    chunk = jax.jit(trainer.run_chunk)
    program = str(jax.make_jaxpr(trainer.run_chunk)(runner, spec.agent_params, spec.env.default_params))
    for _ in range(-(-steps // spec.config.chunk_steps)):
        runner = chunk(runner, spec.agent_params, spec.env.default_params)
    return runner, program.count("pallas_call")


def _assert_carries_agree(a_runner, b_runner, rtol=1e-5, atol=1e-6) -> None:
    for (path, a), (_, b) in zip(_leaves(a_runner), _leaves(b_runner)):
        name = jax.tree_util.keystr(path)
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        if name.split(".")[-1] in ("qpos", "qvel", "obs"):
            np.testing.assert_allclose(b, a, rtol=rtol, atol=atol, err_msg=name)
        else:
            np.testing.assert_array_equal(b, a, err_msg=name)


@pytest.mark.slow
@pytest.mark.parametrize("noise", [CART_RANGES["rand_obs_noise"], [0.0, 0.0]], ids=["noisy", "physics-only"])
def test_the_cartpole_chunk_kernel_follows_the_randomised_plain_path(noise):
    """6 envs, 75 steps in chunks of 25 (every env resets several times, each reset drawing a new cart mass, pole
    mass, pole length and noise level in-kernel): keys, draws, actions, tables, records and counters as the plain
    path's bit for bit, the physics state and the noisy observations to float32 round-off. With the noise level
    pinned at 0 the kernel skips the noise's hashes, at the resets too, and still follows the plain path."""
    spec = _cartpole(randomise=True, **{**CART_RANGES, "rand_obs_noise": noise})
    plain, calls_plain = _carry(spec, "off")
    kernel, calls = _carry(spec, "pallas")
    assert calls_plain == 0 and calls > 0  # the plain path, and the chunk as the kernel
    _assert_carries_agree(plain, kernel)
    assert int(np.asarray(plain.episode).sum()) >= 6  # resets happened, so in-kernel draws were checked
    drawn = np.asarray(kernel.env_state.domain["pole_length"])
    assert ((drawn >= 0.5) & (drawn <= 2.0)).all() and drawn.std() > 0.05
    nominal, _ = _carry(_cartpole(), "pallas")
    assert not np.array_equal(np.asarray(nominal.agent.q), np.asarray(kernel.agent.q))


def test_a_randomised_cartpole_step_at_nominal_factors_is_the_nominal_one_op_by_op():
    """The equations the kernel and the XLA step share (``CartPoleSim.coordinate_step``) given factors of 1 give
    the nominal step's bits, operation by operation (no XLA fusion): :func:`envs.cartpole.dynamics.randomised`
    writes each constant as the nominal one plus a change that is exactly 0 there."""
    sim = jaxrobo.make("CartPoleStayUp-v0", backend="analytic").robot.sim
    state = list(jax.random.normal(jax.random.key(4), (4, 64)) * jnp.array([1.0, 0.3, 1.0, 2.0])[:, None])
    ctrl = (jax.random.uniform(jax.random.key(5), (64,), minval=-3.0, maxval=3.0),)
    one = jnp.ones(64)
    with jax.disable_jit():
        nominal = sim.coordinate_step(*state, ctrl)
        drawn = sim.coordinate_step(*state, ctrl, None, {"cart_mass": one, "pole_mass": one, "pole_length": one})
    for a, b in zip(nominal, drawn):
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a))


def test_cartpole_zero_width_ranges_train_the_nominal_kernel_tables():
    """randomise=true with every range at its nominal value (the defaults): the nominal kernel's tables, records
    and counters bit for bit, its physics state to round-off (the factors are inputs, so XLA compiles the
    equations' constants differently)."""
    nominal, _ = _carry(_cartpole(), "pallas")
    pinned, calls = _carry(_cartpole(randomise=True), "pallas")
    assert calls > 0
    _assert_carries_agree(nominal.replace(env_state=nominal.env_state.replace(domain=())),
                          pinned.replace(env_state=pinned.env_state.replace(domain=())))


def test_the_cartpole_kernel_with_randomisation_lowers_for_the_gpu(monkeypatch):
    """The randomised kernel (in-kernel draws, erfinv of the noise) lowers to one Triton call."""
    spec = _cartpole(n_envs=64, randomise=True, **CART_RANGES)
    trainer = Trainer(spec.env, spec.config, plan=ExecutionPlan.for_run(spec.env, spec.config).replace(
        fused="pallas"))
    runner = jax.jit(trainer.init)(jax.random.key(0), spec.agent_params, spec.env.default_params)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    lowered = jax.jit(trainer.run_chunk).trace(runner, spec.agent_params, spec.env.default_params).lower(
        lowering_platforms=("cuda",))
    assert lowered.as_text().count("__gpu$xla.gpu.triton") == 1


# ---- the plan ----------------------------------------------------------------------------------------------------
def test_the_plan_keeps_the_kernels_for_randomised_runs():
    """On one GPU from 1,024 envs a randomised run of the kernels' tasks gets the kernel, as a nominal run does."""
    goto = jaxrobo.make(GOTO, randomise=True, **GOTO_RANGES)
    assert goto.step_kernel is not None and goto.step_kernel.layout.randomised and goto.step_kernel_refusal is None
    assert physics_kernel(goto) and task_kernel(goto)
    spec = resolve(GOTO, overrides={"n_envs": 4096, "backend": "rigid", "randomise": True, **GOTO_RANGES})
    plan = ExecutionPlan.for_run(spec.env, spec.config, "gpu")
    assert plan.fused == "pallas" and plan.task_kernel
    cart = jaxrobo.make("CartPoleStayUp-v0", backend="analytic", randomise=True, **CART_RANGES)
    assert chunk_kernel_refusal(cart, TrainConfig()) is None
    assert default_fused(cart, "gpu", config=TrainConfig(n_envs=16384)) == "pallas"
    assert not jaxrobo.make(GOTO).step_kernel.layout.randomised  # off: the nominal kernel, no domain inputs
