"""The execution plan: derived choices, repr, validation, how it reaches the trainer, the sweep and the vector env
(without changing a value), grouped stepping, and that no module-global speed knob is left."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrobo.physics import mjx_lean
from jaxrobo.core.config import ConfigError
from jaxrobo.speed.plan import ExecutionPlan, default_env_group, map_groups
from jaxrobo.training.run import resolve
from jaxrobo.training.trainer import Trainer
from jaxrobo.training.train import train

HERE = os.path.abspath(__file__)
ROOT = os.path.dirname(os.path.dirname(HERE))
TINY = dict(n_envs=12, nepisodes=4, nsteps=30, chunk_steps=25, eval_episodes=2, eval_envs=2,
            bins=[3, 6, 8, 10], state_low=[-2.4, -1.0, -0.3, -2.0], state_high=[2.4, 1.0, 0.3, 2.0])
FAST = {"xla_backend_optimization_level": 0}


def _spec(backend="mjx", **overrides):
    return resolve("CartPoleStayUp-v0", overrides={**TINY, "backend": backend, **overrides})


# ---- derivation ------------------------------------------------------------------------------------------------
def test_for_run_derives_the_choices_per_device():
    spec = _spec()
    cpu = ExecutionPlan.for_run(spec.env, spec.config, "cpu")
    assert cpu == ExecutionPlan(env_group=None, unrolled_groups=4, lean_mjx=True, reset_capacity=2, carry_rows=True)
    assert ExecutionPlan.for_run(spec.env, spec.config) == cpu  # the tests run on a CPU
    assert Trainer(spec.env, spec.config).plan == cpu
    shared = _spec(shared_table=True)
    assert not ExecutionPlan.for_run(shared.env, shared.config, "cpu").carry_rows  # other envs change the rows
    assert ExecutionPlan.for_run(spec.env, spec.config.replace(n_envs=17), "cpu").reset_capacity == 3  # ceil(17/8)
    assert ExecutionPlan.for_run(spec.env, spec.config.replace(env_group=5), "cpu").env_group == 5

    gpu = ExecutionPlan.for_run(spec.env, spec.config, "gpu")
    assert gpu == ExecutionPlan(env_group=262_144, unrolled_groups=4, lean_mjx=True, reset_capacity=12,
                                carry_rows=False, compile_beside=True, fixed_kernels=True)
    assert not ExecutionPlan.for_run(spec.env, spec.config, "cpu").fixed_kernels  # XLA's GPU autotuning: GPU only
    assert ExecutionPlan.for_run(spec.env, spec.config.replace(env_group=5), "gpu").env_group == 5
    for backend in ("analytic", "generalized"):  # a closed form, Brax's pipelines: the whole batch
        other = _spec(backend)
        assert ExecutionPlan.for_run(other.env, other.config, "gpu").env_group is None
        assert default_env_group(other.env, "gpu") is None
    assert default_env_group(spec.env, "gpu") == 262_144 and default_env_group(spec.env, "cpu") is None
    # Without a training config (the Gymnasium vector env): grouping and the MJX stage only.
    assert ExecutionPlan.for_run(spec.env, backend="gpu") == ExecutionPlan(env_group=262_144)
    with pytest.raises(ConfigError, match="env_group"):
        resolve("CartPoleStayUp-v0", overrides={"env_group": -1})


def test_gpu_gathers_the_resets_where_the_physics_is_a_kernel():
    """Under ``fused="pallas"`` (the rigid quadcopter on a GPU) from 262,144 envs done envs are gathered and reset,
    an eighth of the batch at most per step, as on a CPU; smaller batches and other GPU runs keep the plain
    select."""
    goto = resolve("QuadcopterGoto-v2", overrides={"n_envs": 262_144, "backend": "rigid"})
    plan = ExecutionPlan.for_run(goto.env, goto.config, "gpu")
    assert (plan.fused, plan.reset_capacity) == ("pallas", 32_768)
    smaller = goto.config.replace(n_envs=262_143)  # pallas, but below the measured batch sizes
    assert ExecutionPlan.for_run(goto.env, smaller, "gpu").reset_capacity == 262_143
    mjx = resolve("QuadcopterGoto-v2", overrides={"n_envs": 262_144, "backend": "mjx"})
    assert ExecutionPlan.for_run(mjx.env, mjx.config, "gpu").reset_capacity == 262_144


def test_the_cart_pole_chunk_kernel_is_a_gpu_default_from_16384_envs():
    """The whole-chunk Pallas kernel compiles ~18 s longer on first use: the default command's 4,096 envs take
    XLA's fused path on a GPU, a run of 16,384 envs or more the kernel (a CPU takes neither)."""
    small, big = _spec("analytic", n_envs=4096), _spec("analytic", n_envs=16_384)
    assert ExecutionPlan.for_run(small.env, small.config, "gpu").fused != "pallas"
    assert ExecutionPlan.for_run(big.env, big.config, "gpu").fused == "pallas"
    assert ExecutionPlan.for_run(big.env, big.config, "cpu").fused == "off"


def test_a_shared_table_on_a_gpu_sums_its_updates_in_order():
    """A shared table's updates meet in a float scatter-add, which a GPU sums as atomics in no fixed order (the same
    seed gave other tables run after run on an H100): on a GPU such a plan sums them in order; per-env tables and a
    CPU keep the scatter-add."""
    shared = _spec(shared_table=True)
    gpu = ExecutionPlan.for_run(shared.env, shared.config, "gpu")
    assert gpu.ordered_sums and "ordered_sums=on" in repr(gpu)  # printed, part of the plan that keys the cache
    assert not ExecutionPlan.for_run(shared.env, shared.config, "cpu").ordered_sums
    spec = _spec()
    assert not ExecutionPlan.for_run(spec.env, spec.config, "gpu").ordered_sums
    with pytest.raises(ValueError, match="ordered_sums=1: expected True or False"):
        ExecutionPlan(ordered_sums=1)


@pytest.mark.slow
def test_sum_in_order_is_the_scatter_add_summed_in_one_order():
    """Whole numbers (exact in any order): equal to the scatter-add bit for bit; fractions: equal to a float64 sum
    within float32 rounding; a training run with a shared table under ordered sums learns what the scatter-add's
    run learns within rounding, and the same seed gives the same tables."""
    from jaxrobo.tabular.learner import sum_in_order

    rng = np.random.default_rng(0)
    index = jnp.asarray(rng.integers(0, 7, 50), jnp.int32)
    whole = jnp.asarray(rng.integers(-5, 6, 50), jnp.float32)
    expected = jnp.zeros(9).at[index].add(whole)
    assert np.array_equal(np.asarray(sum_in_order(index, whole, 9)), np.asarray(expected))
    frac = jnp.asarray(rng.normal(size=50), jnp.float32)
    exact = np.zeros(9)
    np.add.at(exact, np.asarray(index), np.asarray(frac, np.float64))
    np.testing.assert_allclose(np.asarray(sum_in_order(index, frac, 9)), exact, rtol=1e-5, atol=1e-6)
    assert np.asarray(jax.vmap(lambda v: sum_in_order(index, v, 9))(jnp.stack([whole, frac])))[0].tolist() == \
        np.asarray(expected).tolist()
    # Several arrays share one sort; 16-bit and 32-bit sort keys give the same order, so the same sums.
    both = sum_in_order(index, (frac, whole), 9)
    wide = sum_in_order(index, {"f": frac, "w": whole}, 1 << 17)
    assert np.array_equal(np.asarray(both[0]), np.asarray(sum_in_order(index, frac, 9)))
    assert np.array_equal(np.asarray(both[1]), np.asarray(expected))
    assert np.array_equal(np.asarray(wide["f"][:9]), np.asarray(both[0])) and not np.asarray(wide["w"][9:]).any()
    spec = _spec("analytic", shared_table=True)
    base = ExecutionPlan.for_run(spec.env, spec.config, "cpu", compiler_options=FAST)
    plain = train(spec.env, spec.config, spec.agent_params, plan=base)
    ordered = [train(spec.env, spec.config, spec.agent_params, plan=base.replace(ordered_sums=True)) for _ in range(2)]
    assert np.array_equal(ordered[0].q, ordered[1].q)
    np.testing.assert_allclose(ordered[0].q, plain.q, rtol=1e-4, atol=1e-4)


def test_repr_is_short_and_names_every_choice():
    spec = _spec()
    plan = ExecutionPlan.for_run(spec.env, spec.config, "cpu")
    assert repr(plan) == ("ExecutionPlan(env_group=all, unrolled_groups=4, lean_mjx=on, reset_capacity=2, "
                          "carry_rows=on)")
    fast = plan.replace(env_group=3, lean_mjx=False, compiler_options=FAST)
    assert repr(fast) == ("ExecutionPlan(env_group=3, unrolled_groups=4, lean_mjx=off, reset_capacity=2, "
                          "carry_rows=on, compiler_options={xla_backend_optimization_level: 0})")
    assert json.loads(json.dumps(fast.to_dict())) == {
        "env_group": 3, "unrolled_groups": 4, "lean_mjx": False, "reset_capacity": 2, "carry_rows": True,
        "fused": "off", "fused_block": None, "task_kernel": False, "skip_resets": True, "group_resets": True,
        "fast_sincos": True, "ordered_sums": False, "devices": 1, "compile_beside": False, "reuse_traces": False,
        "fixed_kernels": False, "hash_kernel": False, "compiler_options": FAST}
    assert repr(plan.replace(reuse_traces=True)).endswith("carry_rows=on, reuse_traces=on)")
    assert repr(plan.replace(devices=2)).endswith("carry_rows=on, devices=2)")  # named only when more than one
    assert repr(plan.replace(compile_beside=True)).endswith("carry_rows=on, compile_beside=on)")  # only when on
    fixed = plan.replace(fixed_kernels=True)
    assert repr(fixed).endswith("carry_rows=on, fixed_kernels=on)")
    assert fixed.xla_options == {"xla_gpu_autotune_level": 0}
    # XLA's autotuning off comes first: an option the caller gives wins.
    assert fixed.replace(compiler_options={"xla_gpu_autotune_level": 4, **FAST}).xla_options == {
        "xla_gpu_autotune_level": 4, **FAST}
    assert fixed.to_dict()["compiler_options"] == {"xla_gpu_autotune_level": 0}
    assert repr(fixed.replace(hash_kernel=True)).endswith("fixed_kernels=on, hash_kernel=on)")  # only when on
    # The whole-chunk kernel's choices: named only when off under fused="pallas", where they are read.
    kernel = plan.replace(fused="pallas", fused_block=16, group_resets=False, fast_sincos=False)
    assert repr(kernel).endswith("fused=pallas, fused_block=16, group_resets=off, fast_sincos=off)")
    assert repr(plan.replace(skip_resets=False)) == repr(plan)
    with pytest.raises(ValueError, match=r"ExecutionPlan skip_resets=1: expected True or False"):
        plan.replace(skip_resets=1)


def test_plans_are_validated_frozen_and_hashable():
    plan = ExecutionPlan(compiler_options={"b": 1, "a": "x"})
    assert plan.compiler_options == (("a", "x"), ("b", 1)) and plan.xla_options == {"a": "x", "b": 1}
    assert plan == ExecutionPlan(compiler_options=[("b", 1), ("a", "x")]) and len({plan, plan.replace()}) == 1
    assert ExecutionPlan(compiler_options={}).compiler_options is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.env_group = 3
    for bad, field in (({"env_group": 0}, "env_group"), ({"reset_capacity": -1}, "reset_capacity"),
                       ({"unrolled_groups": 0}, "unrolled_groups"), ({"lean_mjx": 1}, "lean_mjx"),
                       ({"carry_rows": "yes"}, "carry_rows"), ({"compiler_options": {"a": []}}, "compiler_options"),
                       ({"devices": 0}, "devices"),
                       ({"env_group": True}, "env_group")):
        with pytest.raises(ValueError, match=f"ExecutionPlan {field}="):
            ExecutionPlan(**bad)
    with pytest.raises(ValueError, match="ExecutionPlan fixed_kernels=0: expected True or False"):
        ExecutionPlan(fixed_kernels=0)


def test_tracing_sets_the_mjx_choice_for_its_block_only():
    stock = ExecutionPlan(lean_mjx=False)
    assert mjx_lean.wanted()
    with stock.tracing() as entered:
        assert entered is stock and not mjx_lean.wanted()
        with ExecutionPlan().tracing():
            assert mjx_lean.wanted()
        assert not mjx_lean.wanted()
    assert mjx_lean.wanted()
    seen = stock.traced(lambda x: (mjx_lean.wanted(), x))(1)
    assert seen == (False, 1) and mjx_lean.wanted()


def test_what_tracing_sets_is_what_keys_an_envs_shared_reset(monkeypatch):
    """An env's reset jitted on its own is kept per :func:`jaxrobo.task.env.trace_choices`: every trace-time
    switch the plan's ``tracing`` sets is in that key (a switch added to ``tracing`` and not to the key would let
    one plan's trace of the reset serve another plan's program), and the resets are shared inside it only."""
    import contextvars
    import itertools

    from jaxrobo.core import hash_kernel
    from jaxrobo.task import env as task_env

    monkeypatch.setattr(hash_kernel, "usable", lambda: True)  # as on a CUDA GPU (nothing is lowered here)
    seen: dict = {}
    for lean, fused, task_kernel, kernel_hash in itertools.product((True, False), ("off", "xla", "pallas"),
                                                                  (False, True), (False, True)):
        with ExecutionPlan(lean_mjx=lean, fused=fused, task_kernel=task_kernel, hash_kernel=kernel_hash).tracing():
            switches = tuple(sorted((var.name, value) for var, value in contextvars.copy_context().items()
                                    if var.name.startswith("jaxrobo_") and var.name != "jaxrobo_shared_resets"))
            assert task_env._SHARED_RESETS.get()
            seen.setdefault(task_env.trace_choices(), set()).add(switches)
    assert all(len(switches) == 1 for switches in seen.values()), seen  # one key, one set of switches
    assert len(seen) > 1 and not task_env._SHARED_RESETS.get()


# ---- grouped stepping ------------------------------------------------------------------------------------------
def test_map_groups_applies_fn_slice_by_slice():
    tree = {"x": jnp.arange(7.0), "y": jnp.arange(14).reshape(7, 2)}
    # y grows by the number of rows fn saw at once, which shows the slicing
    fn = lambda t: {"x": t["x"] * 2 + t["y"][:, 0], "y": t["y"] + t["x"].shape[0]}  # noqa: E731
    for group, rows_seen in ((3, [3, 3, 3, 3, 3, 3, 1]), (7, [7] * 7), (8, [7] * 7), (None, [7] * 7)):
        # groups written out (the plan's default 4 of them), in a loop of blocks of 1 or 2 groups, or all written out
        for unrolled in (ExecutionPlan.unrolled_groups, 1, 2, 8):
            out = jax.jit(lambda t, g=group, u=unrolled: map_groups(fn, t, g, u))(tree)
            np.testing.assert_array_equal(out["x"], fn(tree)["x"])
            np.testing.assert_array_equal(out["y"], tree["y"] + np.array(rows_seen)[:, None])
    with pytest.raises(ValueError, match="unrolled=0"):
        map_groups(fn, tree, 3, unrolled=0)


# ---- the plan reaches every consumer and changes no value -----------------------------------------------------
@pytest.mark.parametrize("beside", [False, pytest.param(True, marks=pytest.mark.slow)])  # beside: a GPU default
def test_train_under_another_plan_gives_the_recorded_values(monkeypatch, beside):
    """Groups of 3 (one written out, then a loop), one gathered reset per step, no carried rows and stock MJX give
    the values recorded before the plan existed (the fingerprint of the closed-form cart-pole case), and
    ``train`` hands its plan to the trainer and traces under it; so does the evaluation compiled beside the
    training chunk (``compile_beside``)."""
    import importlib.util

    path = os.path.join(ROOT, "scripts", "fingerprints.py")
    module_spec = importlib.util.spec_from_file_location("fingerprints", path)
    fingerprints = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(fingerprints)
    with open(os.path.join(ROOT, "tests", "data", "fingerprints.json")) as f:
        recorded = json.load(f)
    case = next(c for c in fingerprints.cases() if fingerprints.name(c) ==
                "CartPoleStayUp-v0/default/qlearn/env.backend=analytic")
    spec = resolve(case["env_id"], case["preset"], {**fingerprints.SMALL, **case["extra"]}, agent=case["agent"])
    plan = ExecutionPlan(env_group=3, unrolled_groups=1, lean_mjx=False, reset_capacity=1, carry_rows=False,
                         compile_beside=beside)
    built, chosen = [], []
    init, choose = Trainer.__init__, mjx_lean.choose

    def spy_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        built.append(self.plan)

    def spy_choose(enabled):
        chosen.append(enabled)
        return choose(enabled)

    monkeypatch.setattr(Trainer, "__init__", spy_init)
    monkeypatch.setattr(mjx_lean, "choose", spy_choose)
    r = train(spec.env, spec.config, spec.agent_params, plan=plan)
    assert built == [plan] and chosen and not any(chosen)
    assert r.summary()["execution_plan"] == repr(plan)  # summary.json says how the run ran
    h = hashlib.sha256()
    for arr in (r.q, r.returns, r.lengths, r.terminated, r.nan_episodes, np.int64(r.env_steps),
                r.eval_returns, r.eval_lengths):
        a = np.ascontiguousarray(np.asarray(arr))
        h.update(str((a.shape, a.dtype.str)).encode() + a.tobytes())
    assert h.hexdigest() == recorded[fingerprints.name(case)]


@pytest.mark.parametrize("lean", [True, False])
def test_the_trainer_traces_mjx_steps_as_its_plan_says(mjx_step_spy, lean):
    """Whoever traces the trainer's chunk (train, the sweep, a benchmark), its MJX steps follow the plan."""
    spec = _spec()
    trainer = Trainer(spec.env, spec.config, plan=ExecutionPlan.for_run(spec.env, spec.config).replace(lean_mjx=lean))
    swapped = mjx_step_spy
    ap, ep = spec.agent_params, spec.env.default_params
    runner = jax.eval_shape(trainer.init, jax.random.key(0), ap, ep)
    jax.eval_shape(trainer.run_chunk, runner, ap, ep)  # traced outside any plan block
    assert swapped and set(swapped) == {lean}


def test_trainer_choices_read_the_plan():
    spec = _spec("analytic")
    plan = ExecutionPlan(env_group=3, reset_capacity=None, carry_rows=True)
    trainer = Trainer(spec.env, spec.config, plan=plan)
    assert (trainer.env_group, trainer.reset_capacity, trainer.carry_rows) == (3, 12, True)
    trainer.env_group = None  # assigning a choice replaces the plan
    assert trainer.plan == plan.replace(env_group=None)
    shared = _spec("analytic", shared_table=True)
    assert not Trainer(shared.env, shared.config, plan=plan).carry_rows  # never with a shared table


def test_the_sweep_compiles_each_group_under_a_plan_with_its_compiler_options(monkeypatch):
    from jaxrobo.training import sweep

    seen = []

    def record(self, *args, **kwargs):
        seen.append(self.trainer.plan)
        return {m: np.zeros(self.n_rows) for m in sweep.METRICS}

    monkeypatch.setattr(sweep.GroupRunner, "run", record)
    plan = sweep.plan_sweep("CartPoleStayUp-v0", [{"alpha": 0.1}, {"alpha": 0.5}], [0],
                            overrides={"n_envs": 2, "nepisodes": 2, "nsteps": 10, "backend": "analytic"},
                            compiler_options=FAST)
    sweep.run_plan(plan)
    spec = plan.groups[0].spec
    assert seen == [ExecutionPlan.for_run(spec.env, spec.config, compiler_options=FAST)]
    assert seen[0].xla_options == FAST and plan.settings["compiler_options"] == FAST


def test_the_vector_env_steps_as_its_plan_says_with_the_same_values():
    from jaxrobo.interop.gym_adapter import JaxroboVectorEnv

    kw = dict(num_envs=3, overrides={"max_episode_steps": 6})  # the size test_gym_adapter compiles
    whole = JaxroboVectorEnv("CartPoleStayUp-v0", **kw)
    plan = ExecutionPlan(env_group=2, unrolled_groups=1, lean_mjx=False)
    grouped = JaxroboVectorEnv("CartPoleStayUp-v0", plan=plan, **kw)
    assert whole.plan == ExecutionPlan.for_run(whole.jax_env) and grouped.plan is plan
    assert whole._fns is not grouped._fns
    outs = []
    for venv in (whole, grouped):
        obs, _ = venv.reset(seed=3)
        rows = [obs]
        for t in range(9):
            obs, rew, term, trunc, _ = venv.step(np.arange(3) % venv.single_action_space.n)
            rows += [obs, rew, term, trunc]
        outs.append(rows)
    for a, b in zip(*outs):
        np.testing.assert_array_equal(a, b)


# ---- no module-global speed knobs ------------------------------------------------------------------------------
def test_no_module_global_speed_knob_is_left():
    from jaxrobo.task import env
    from jaxrobo.physics import sim
    from jaxrobo.training import sweep

    for module, name in ((sim, "LEAN_MJX"), (sim, "lean_mjx"), (env, "UNROLLED_GROUPS"), (env, "GPU_ENV_GROUP"),
                         (env, "step_batch"), (env, "map_groups"), (sweep, "COMPILER_OPTIONS")):
        assert not hasattr(module, name), f"{module.__name__}.{name}"
    pattern = re.compile(r"\b(LEAN_MJX|UNROLLED_GROUPS|GPU_ENV_GROUP|COMPILER_OPTIONS)\b")
    found = []
    for folder in ("jaxrobo", "envs", "agents", "benchmarks", "tests", "scripts"):
        for base, _, files in os.walk(os.path.join(ROOT, folder)):
            for f in files:
                path = os.path.join(base, f)
                if f.endswith(".py") and path not in (os.path.join(ROOT, "jaxrobo", "plan.py"), HERE):
                    with open(path) as fh:
                        found += [f"{path}: {m}" for m in pattern.findall(fh.read())]
    assert found == []


def test_automatic_devices_keep_a_shared_table_on_one_device(monkeypatch):
    """Several devices: per-env tables split over them; a shared table (one table every env feeds) stays on one
    device unless `devices` is set, so its sums are added in the one-device order whatever the device count."""
    monkeypatch.setattr(jax, "device_count", lambda *a, **k: 4)
    per_env = resolve("CartPoleStayUp-v0", overrides=dict(n_envs=8, backend="analytic"))
    shared = resolve("QuadcopterGoto-v2", overrides=dict(n_envs=8))
    assert shared.config.shared_table and not per_env.config.shared_table
    assert ExecutionPlan.for_run(per_env.env, per_env.config, "cpu").devices == 4
    assert ExecutionPlan.for_run(shared.env, shared.config, "cpu").devices == 1
    asked = resolve("QuadcopterGoto-v2", overrides=dict(n_envs=8, devices=4))
    assert ExecutionPlan.for_run(asked.env, asked.config, "cpu").devices == 4
