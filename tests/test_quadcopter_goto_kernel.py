"""``ExecutionPlan(fused="pallas", task_kernel=True)`` for the Goto tasks: the whole step as one Pallas kernel
(:mod:`envs.quadcopter.goto_kernel`), run here interpreted on a CPU and held to the task's own hooks (the plain
``TaskEnv.step``) as its oracle.

The kernel flies the robot with the XLA step's own controller and physics (:mod:`envs.quadcopter.dynamics`) and
writes the task's hooks per coordinate; XLA fuses the two programs differently (contracting a multiply and an add
within a fusion into one FMA) and reads the sensors through other operations, so a step agrees to float32
round-off; the discrete parts (done flags, arrivals, crashes, the NaN guard) agree exactly for
the states here, none of which sits on a threshold to round-off.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs.quadcopter.goto_twist import QuadcopterGotoTwist
from envs.quadcopter.goto_kernel import Layout, kernel_step, supports, task_step
from envs.quadcopter.kernel import constants_of
from jaxrobo.physics import fused
from jaxrobo.speed.plan import ExecutionPlan, task_kernel
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer

TINY = dict(n_envs=4, nepisodes=3, nsteps=20, chunk_steps=15, eval_episodes=2, eval_envs=2, backend="rigid")
#: The configurations the step is checked in: v1 as preset (one cylinder, written out), v2 with a mix of kinds
#: beyond the written-out count (the in-kernel loop over obstacles), v1 with boxes and none.
CASES = {"v1": ("QuadcopterGoto-v1", {}),
         "v2-mixed": ("QuadcopterGoto-v2", dict(n_obstacles=3, obstacle_kind="mixed")),
         "v1-box": ("QuadcopterGoto-v1", dict(n_obstacles=2, obstacle_kind="box", obstacle_placement="random")),
         "v2-none": ("QuadcopterGoto-v2", dict(n_obstacles=0))}


@functools.lru_cache(maxsize=None)
def _spec(case: str):
    env_id, overrides = CASES[case]
    return resolve(env_id, overrides={**TINY, **overrides})


@functools.lru_cache(maxsize=None)
def _states(case: str, n: int = 160):
    """Reset states moved about: near and inside obstacles, at the goal, on the ground, tilted past the limit,
    outside the workspace, and one non-finite; random actions."""
    env, p = _spec(case).env, _spec(case).env.default_params
    st = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(3), n), p)
    k = jax.random.split(jax.random.key(4), 6)
    pos = st.pipeline_state.qpos[:, :3] + jax.random.normal(k[0], (n, 3)) * jnp.array([2.5, 2.5, 0.5])
    if st.task.obstacles.center.shape[1]:  # a quarter next to or inside an obstacle
        near = st.task.obstacles.center[:, 0] + jax.random.normal(k[1], (n, 3)) * jnp.array([0.5, 0.5, 0.0])
        pos = jnp.where((jnp.arange(n) % 4 == 0)[:, None], near.at[:, 2].set(pos[:, 2]), pos)
    pos = jnp.where((jnp.arange(n) % 7 == 1)[:, None], st.task.goal + 0.1, pos)  # arriving
    pos = pos.at[::11, 2].set(0.1)  # on the ground
    pos = pos.at[5::13, 0].set(9.0)  # outside the workspace
    quat = st.pipeline_state.qpos[:, 3:]
    tilted = jnp.array([np.cos(0.45), np.sin(0.45), 0.0, 0.0], jnp.float32)  # roll 0.9 rad > max_incl
    quat = jnp.where((jnp.arange(n) % 9 == 2)[:, None], tilted, quat)
    qvel = jax.random.normal(k[2], (n, 6)) * 0.5
    qvel = qvel.at[3, 4].set(jnp.nan)  # the NaN guard
    st = st.replace(pipeline_state=st.pipeline_state.replace(qpos=jnp.concatenate([pos, quat], 1), qvel=qvel))
    return st, jax.random.randint(k[3], (n,), 0, 5)


@functools.lru_cache(maxsize=None)
def _stepped(case: str, task: bool):
    env, p = _spec(case).env, _spec(case).env.default_params

    def step(s, a):
        with fused.choose("pallas" if task else "off", task):
            return jax.vmap(env.step, in_axes=(0, 0, None))(s, a, p)

    return jax.jit(step)(*_states(case))


def _assert_steps_agree(ref, got) -> None:
    leaves = jax.tree_util.tree_flatten_with_path(ref)[0]
    for (path, a), b in zip(leaves, jax.tree.leaves(got)):
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        name, a, b = jax.tree_util.keystr(path), np.asarray(a), np.asarray(b)
        if name == ".obs":
            # The sonars (and v2's goal_clear ray) from column 3 on: a level ray grazing an obstacle has a range
            # whose derivative in the pose is unbounded at tangency, so on a GPU the last-ulp differences of
            # Triton's and XLA's arithmetic move a few readings by up to a millimetre (0.6 mm on an H100; the
            # sonar bins are 0.5-1 m wide). They are held to 1 cm, the goal's terms to round-off.
            np.testing.assert_allclose(b[:, 3:], a[:, 3:], rtol=0, atol=1e-2, err_msg=name + " sonars")
            a, b = a[:, :3], b[:, :3]
        if np.issubdtype(a.dtype, np.floating):
            # 30 substeps' round-off (see tests/test_quadcopter_kernel.py), then the distances read from them.
            np.testing.assert_allclose(b, a, rtol=2e-5, atol=5e-5, err_msg=name)
        else:
            np.testing.assert_array_equal(b, a, err_msg=name)


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_the_kernel_step_agrees_with_the_hooks(case):
    """160 states (not a multiple of the block) with crashes into obstacles and the ground, arrivals, tilt and
    workspace limits and a NaN: the kernel's whole step is the hooks' step to float32 round-off, and its discrete
    outcomes are the same."""
    ref, got = _stepped(case, False), _stepped(case, True)
    _assert_steps_agree(ref, got)
    term, nan = np.asarray(ref.terminated), np.asarray(ref.physics_nan)
    assert nan[3] and nan.sum() == 1 and np.asarray(got.obs)[3].tolist() == np.asarray(_states(case)[0].obs)[3].tolist()
    assert 0 < term.sum() < term.size  # the states do reach the outcomes
    assert np.asarray(ref.task.arrived).any() and np.asarray(ref.task.crashed).any()


@pytest.mark.slow
def test_the_per_coordinate_step_runs_on_plain_arrays():
    """:func:`task_step` outside any kernel, on ``[n]`` arrays (as the kernel runs it on a block), gives the
    kernel's values."""
    env = _spec("v2-mixed").env
    p = env.default_params
    st, a = _states("v2-mixed")
    layout = Layout(3, "mixed", True)
    obs = st.task.obstacles

    def run(st, a):
        cols = lambda x: [x[:, j] for j in range(x.shape[1])]  # noqa: E731
        task = {"goal": cols(st.task.goal), "prev_dist": st.task.prev_dist, "arrived": st.task.arrived,
                "crashed": st.task.crashed, "prev_bearing": st.task.prev_bearing, "prev_dz": st.task.prev_dz}
        ob = lambda i: (obs.kind[:, i], cols(obs.center[:, i]), cols(obs.size[:, i]), obs.active[:, i])  # noqa: E731
        return task_step(constants_of(env.robot), layout, cols(st.pipeline_state.qpos), cols(st.pipeline_state.qvel),
                         a, lambda ok: cols(st.obs), task, {n: getattr(p, n) for n in layout.param_names}, ob)

    out = jax.jit(run)(st, a)
    got = _stepped("v2-mixed", True)
    np.testing.assert_allclose(np.stack(out["obs"], 1), np.asarray(got.obs), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(out["reward"], np.asarray(got.reward), rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(out["terminated"], np.asarray(got.terminated))


@pytest.mark.slow
def test_a_sweep_around_the_batch_is_one_call_with_its_own_parameters():
    """A vmap over configurations (as a sweep runs one) with a batched parameter makes one kernel call and gives
    each configuration's own flat-batch step (to round-off); an unbatched step agrees to round-off."""
    env = _spec("v1").env
    st, a = _states("v1", 160)
    st, a = jax.tree.map(lambda x: x[:24], st), a[:24]
    p = env.default_params
    speeds = jnp.array([0.5, 1.0, 2.0], jnp.float32)
    split = lambda x: x.reshape((3, 8) + x.shape[1:])  # noqa: E731

    def sweep(s, a, speed):
        return jax.vmap(lambda s, a: kernel_step(env, s, a, p.replace(speed_value=speed)))(s, a)

    nested = jax.jit(jax.vmap(sweep))(jax.tree.map(split, st), split(a), speeds)
    program = str(jax.make_jaxpr(jax.vmap(sweep))(jax.tree.map(split, st), split(a), speeds))
    assert program.count("pallas_call") == 1
    for i in range(3):
        flat = jax.jit(sweep)(jax.tree.map(lambda x: split(x)[i], st), split(a)[i], speeds[i])
        for x, y in zip(jax.tree.leaves(flat), jax.tree.leaves(jax.tree.map(lambda x: x[i], nested))):
            if not jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
                # To round-off: the interpreter compiles a per-env and a shared parameter differently.
                np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-5, atol=1e-6)
    one = jax.jit(lambda s, a: kernel_step(env, s, a, p))(jax.tree.map(lambda x: x[9], st), a[9])
    ref = jax.jit(jax.vmap(lambda s, a: kernel_step(env, s, a, p)))(st, a)
    np.testing.assert_allclose(np.asarray(one.obs), np.asarray(ref.obs)[9], rtol=1e-6, atol=1e-6)


def _plan(spec, **changes):
    return ExecutionPlan.for_run(spec.env, spec.config).replace(**changes)


def test_the_plan_chooses_it_where_the_task_has_one_and_refuses_it_elsewhere():
    spec = resolve("QuadcopterGoto-v2", overrides={"n_envs": 262_144, "backend": "rigid"})
    plan = ExecutionPlan.for_run(spec.env, spec.config, "gpu")
    assert plan.fused == "pallas" and plan.task_kernel and "task_kernel=on" in repr(plan)
    assert "task_kernel" not in repr(plan.replace(task_kernel=False))  # another program, another cache key
    mjx = resolve("QuadcopterGoto-v2", overrides={"n_envs": 262_144, "backend": "mjx"})
    assert not task_kernel(mjx.env) and not ExecutionPlan.for_run(mjx.env, mjx.config, "gpu").task_kernel
    assert "backend='mjx'" in supports(mjx.env)
    twist = QuadcopterGotoTwist()  # a subclass with another action: no task kernel, the robot's kernel still
    assert twist.step_kernel is None and "overrides _set_action" in supports(twist)
    show = resolve("QuadcopterLiveShow-v0", overrides={**TINY, "shared_table": True})
    with pytest.raises(ValueError, match=r"task_kernel=True: QuadcopterLiveShow has no kernel for its whole step"):
        Trainer(show.env, show.config, plan=_plan(show, fused="pallas", task_kernel=True))
    Trainer(show.env, show.config, plan=_plan(show, fused="pallas"))  # the control-step kernel alone


# Training through the task kernel follows the plain path: tests/test_quadcopter_kernel.py (both kernels).


@pytest.mark.parametrize("case", ["v1", "v2-mixed"])
def test_it_lowers_for_the_gpu_through_triton(case, monkeypatch):
    """The kernel the GPU would run (not interpreted) lowers to one Triton call: the float remainder of the
    bearing's wrap, the in-kernel loops over substeps and obstacles and the integer loads all have lowerings."""
    env, p = _spec(case).env, _spec(case).env.default_params
    st, a = _states(case)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    step = jax.vmap(lambda s, a: kernel_step(env, s, a, p))
    text = jax.jit(step).trace(st, a).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count("__gpu$xla.gpu.triton") == 1
