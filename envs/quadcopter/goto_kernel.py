"""The Goto tasks' whole control step as one Pallas kernel: action → Twist, the robot's control step (every
substep of controller and rigid physics), the observation (goal distance and bearing, the level sonars against
the obstacles and the ground, v2's ``goal_clear``), the outcome (crash, limits, arrival), the reward, the task
variables and the NaN guard, for a block of envs, each env reading its state and task variables once and
writing its new ones once.

Why: with only the control step in a kernel (:mod:`envs.quadcopter.kernel`), the rest of the task's step stayed
XLA's: some 30 batch-wide kernels a step (transposes, the sonar's 3x3 GEMM, the concatenations building the
observation, reductions over the obstacles), each moving part of every env's state through memory. Here the
task's step is one kernel and only the learner, the discretiser and the reset remain around it.

What it computes: nothing of its own. :func:`task_step` composes the task's step as
:mod:`envs.quadcopter.goto_step` writes it once per coordinate (the action map, the observation, the outcome, the
reward: the functions the hooks of :class:`envs.quadcopter.goto.QuadcopterGoto` and the native port run too) with
the robot's control step (:func:`envs.quadcopter.kernel.control_step`: :mod:`envs.quadcopter.dynamics`' controller
and physics) and :meth:`jaxrobo.task.env.TaskEnv.step`'s NaN guard, on arrays of any shape (the tests run it on a
CPU against the hooks). What only a kernel needs stays here: the obstacles read by index, unrolled or in a loop
(the hooks vmap over them), and the guard written with ``abs(x) < inf`` (Triton has no ``isfinite``). The kernel
agrees with the XLA step to float32 round-off, not bit for bit (the two programs are fused differently, and a GPU
takes ``atan2``/``sin``/``cos`` from another library).

Domain randomisation (``randomise=true``): the kernel is built with :attr:`Layout.randomised` and reads each
env's drawn physics as per-env inputs (:data:`envs.quadcopter.kernel.PHYSICS`, from the env state's ``domain``
through the robot's ``sim_physics``, as the XLA step); :func:`kernel_step` adds the observation noise to the
kernel's observation as :meth:`jaxrobo.task.env.TaskEnv.step` adds it.

Scope (:func:`supports`): the Goto tasks with the seed's five discrete actions (v1, v2), backend ``rigid``, any
``n_obstacles`` (0-32; more than :data:`UNROLL_OBSTACLES` run as a loop inside the kernel), kinds ``cylinder``,
``box`` or ``mixed``. A subclass that overrides a hook gets no kernel (its meaning would be lost): the plan
then keeps the physics-only kernel. The obstacles' ``kind`` is read only for ``mixed``: the other two layouts
are one kind by construction (:meth:`envs.quadcopter.goto.QuadcopterGoto._obstacles`).

How it is used: :class:`envs.quadcopter.goto.QuadcopterGoto` builds :func:`make_task_step` as its
``step_kernel``; under ``ExecutionPlan(fused="pallas", task_kernel=True)`` (:mod:`jaxrobo.speed.plan`, the default
with ``fused="pallas"`` where the task has one) its ``step`` runs :func:`kernel_step`, which a vmapped step
turns into one kernel call over the whole batch (and over any vmap around it, as a sweep's).

Public surface: :func:`supports`, :func:`make_task_step`, :func:`kernel_step`, :func:`task_step`,
:class:`Layout`, :data:`UNROLL_OBSTACLES`.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from envs.quadcopter.geometry import euler
from envs.quadcopter.goto_step import V1_PARAMS, V2_PARAMS, kinds_of, observe, outcome, reward, twist
from envs.quadcopter.kernel import BLOCK, PHYSICS, Constants, constants_of, control_step

#: Obstacles written out one after another in the kernel; more run in a loop (a long unrolled body compiles
#: slowly and gains nothing once the loop's few instructions are amortised over an obstacle's ray tests).
UNROLL_OBSTACLES = 2

#: The hooks whose meaning the kernel holds: a subclass overriding one of them gets no kernel.
HOOKS = ("step", "_set_action", "_p", "_observe", "_get_obs", "_outcome", "_is_done", "_compute_reward")


@dataclasses.dataclass(frozen=True)
class Layout:
    """What the kernel is specialised for (static): obstacles per env, their kind, v2's additions, and whether
    each env brings its drawn physics (domain randomisation: the inputs :data:`envs.quadcopter.kernel.PHYSICS`;
    off, the kernel has none of them and is the program it was before randomisation existed)."""

    n_obstacles: int
    obstacle_kind: str  # "cylinder", "box" or "mixed"
    v2: bool
    randomised: bool = False

    @property
    def param_names(self) -> tuple[str, ...]:
        return V2_PARAMS if self.v2 else V1_PARAMS

    @property
    def obs_size(self) -> int:
        return 8 if self.v2 else 7


def supports(env: Any) -> str | None:
    """None if ``env``'s step can run as the task kernel, else why not (a sentence)."""
    variant = getattr(env, "step_kernel_variant", None)
    if variant is None:
        return f"{type(env).__name__} declares no task kernel (only the Goto tasks with discrete actions do)"
    if env.options.backend != "rigid":
        return f"backend={env.options.backend!r}: the task kernel runs the 'rigid' physics only"
    owner = next(cls for cls in type(env).__mro__ if "step_kernel_variant" in cls.__dict__)
    for cls in type(env).__mro__:
        if cls is owner:
            break
        changed = [h for h in HOOKS if h in cls.__dict__]
        if changed:
            return f"{cls.__name__} overrides {', '.join(changed)}, whose meaning the task kernel would not hold"
    return None


# ---- the task's step, per coordinate ---------------------------------------------------------------------
def _finite(x):
    return jnp.abs(x) < np.inf  # False for NaN and ±inf (Triton has no isfinite)


#: Obstacle accessor: index → ``(kind or None, center [3], size [3], active)``, each per coordinate.
Obstacle = Callable[[Any], tuple[Any, list, list, Any]]


def task_step(c: Constants, layout: Layout, q: Sequence, v: Sequence, action, old_obs: Callable[[Any], Sequence],
              task: dict, p: dict, obstacle: Obstacle, physics: dict | None = None) -> dict:
    """One Goto step per coordinate, on arrays of any (common) shape: ``q`` (7), ``v`` (6) the robot's state,
    ``action`` int, ``old_obs(ok)`` the last observation (kept where ``ok``, the new state is finite, is False:
    the kernel reads it only there), ``task`` the
    per-step task variables (``goal`` [3], ``prev_dist``, ``arrived``, ``crashed`` as bools; v2 ``prev_bearing``,
    ``prev_dz``), ``p`` the parameters by name, ``obstacle`` the obstacles' accessor, ``physics`` the env's
    drawn physics (domain randomisation; None: nominal). Returns the new ``q``, ``v``, ``obs``, ``reward``,
    ``terminated``, ``nan`` (the guard fired) and the task variables. The observation noise of a randomised task
    is not added here: :func:`kernel_step` adds it around the kernel, as :meth:`jaxrobo.task.env.TaskEnv.step`
    does after the hooks."""
    q, v = control_step(c, q, v, twist(jnp, action, p["speed_value"]), physics)
    roll, pitch, yaw = euler(jnp, q[3], q[4], q[5], q[6])
    pos = q[:3]

    def fold(distances, nearest):  # the obstacles by index: unrolled, or a loop inside the kernel
        def one(i, carry):
            return tuple(jnp.minimum(m, t) for m, t in zip(carry, distances(*obstacle(i))))

        if layout.n_obstacles > UNROLL_OBSTACLES:
            return jax.lax.fori_loop(0, layout.n_obstacles, one, nearest)
        for i in range(layout.n_obstacles):
            nearest = one(i, nearest)
        return nearest

    obs, dist, point = observe(jnp, pos, yaw, v[2], task["goal"], p, layout.v2, kinds_of(layout.obstacle_kind), fold)
    arrived, failed = outcome(jnp, pos, roll, pitch, dist, point, p)
    rew, new_task = reward(jnp, p, task, obs, dist, pos[2], arrived, failed, layout.v2)
    # TaskEnv.step's guard: a non-finite state ends the episode with zero reward and the last finite observation.
    ok = _finite(q[0])
    for value in list(q[1:]) + list(v) + obs:
        ok = ok & _finite(value)
    obs = [jnp.where(ok, o, old) for o, old in zip(obs, old_obs(ok))]
    new_task = {name: jnp.where(ok, value, task[name]) for name, value in new_task.items()}  # the task as it was
    return {"q": q, "v": v, "obs": obs, "reward": jnp.where(ok, rew, 0.0), "terminated": arrived | failed | ~ok,
            "nan": ~ok, "task": new_task}


# ---- the batch kernel ------------------------------------------------------------------------------------
F32, I32, BOOL = jnp.float32, jnp.int32, jnp.bool_


def _fields(layout: Layout) -> tuple[list, list]:
    """The kernel's per-env inputs and outputs: ``(name, values per env, dtype)``, each the task's own dtype (so
    XLA converts nothing around the call)."""
    k = layout.n_obstacles
    extra = [("prev_bearing", 1, F32), ("prev_dz", 1, F32)] if layout.v2 else []
    ins = [("qpos", 7, F32), ("qvel", 6, F32), ("action", 1, I32), ("obs", layout.obs_size, F32), ("goal", 3, F32),
           ("prev_dist", 1, F32), ("arrived", 1, BOOL), ("crashed", 1, BOOL)] + extra
    if k:
        ins += ([("kind", k, I32)] if layout.obstacle_kind == "mixed" else []) + \
            [("center", 3 * k, F32), ("size", 3 * k, F32), ("active", k, BOOL)]
    if layout.randomised:
        ins += [(name, width, F32) for name, width in PHYSICS]
    outs = [("qpos", 7, F32), ("qvel", 6, F32), ("obs", layout.obs_size, F32), ("reward", 1, F32),
            ("terminated", 1, BOOL), ("nan", 1, BOOL), ("prev_dist", 1, F32), ("arrived", 1, BOOL),
            ("crashed", 1, BOOL)] + extra
    return ins, outs


def _zero(dtype):
    return False if dtype == BOOL else 0 if dtype == I32 else 0.0


def _kernel(c: Constants, layout: Layout, n: int, block: int, params_per_env: bool) -> Callable:
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    ins, outs = _fields(layout)
    n_params = len(layout.param_names)

    def kernel(*refs):
        in_refs = dict(zip([f[0] for f in ins] + ["params"], refs[:len(ins) + 1]))
        out_refs = dict(zip([f[0] for f in outs], refs[len(ins) + 1:]))
        env = pl.program_id(0) * block + jax.lax.iota(jnp.int32, block)
        mask = env < n

        def load(name, width, j, dtype):
            return plgpu.load(in_refs[name].at[env * width + j], mask=mask, other=_zero(dtype))

        skip = {"obs", "kind", "center", "size", "active"} | {name for name, _ in PHYSICS}
        row = {name: [load(name, width, j, dtype) for j in range(width)]
               for name, width, dtype in ins if name not in skip}
        physics = None
        if layout.randomised:  # each env's drawn physics (masked lanes read 1: finite, and never stored)
            loaded = {name: [plgpu.load(in_refs[name].at[env * width + j], mask=mask, other=1.0)
                             for j in range(width)] for name, width in PHYSICS}
            physics = {name: values if len(values) > 1 else values[0] for name, values in loaded.items()}

        def old_obs(ok):  # read only where the guard fires: a warp of finite states loads nothing
            return [plgpu.load(in_refs["obs"].at[env * layout.obs_size + j], mask=mask & ~ok, other=0.0)
                    for j in range(layout.obs_size)]

        stride = n_params if params_per_env else 0
        p = {name: plgpu.load(in_refs["params"].at[env * stride + j], mask=mask, other=0.0)
             for j, name in enumerate(layout.param_names)}
        k = layout.n_obstacles

        def obstacle(i):
            kind = load("kind", k, i, I32) if layout.obstacle_kind == "mixed" else None
            center = [load("center", 3 * k, 3 * i + j, F32) for j in range(3)]
            size = [load("size", 3 * k, 3 * i + j, F32) for j in range(3)]
            return kind, center, size, load("active", k, i, BOOL)

        task = {"goal": row["goal"], "prev_dist": row["prev_dist"][0], "arrived": row["arrived"][0],
                "crashed": row["crashed"][0]}
        if layout.v2:
            task.update(prev_bearing=row["prev_bearing"][0], prev_dz=row["prev_dz"][0])
        out = task_step(c, layout, row["qpos"], row["qvel"], row["action"][0], old_obs, task, p, obstacle, physics)
        values = {"qpos": out["q"], "qvel": out["v"], "obs": out["obs"], "reward": [out["reward"]],
                  "terminated": [out["terminated"]], "nan": [out["nan"]],
                  **{name: [value] for name, value in out["task"].items()}}
        for name, width, dtype in outs:
            for j, value in enumerate(values[name]):
                plgpu.store(out_refs[name].at[env * width + j], value.astype(dtype), mask=mask)

    return kernel


@dataclasses.dataclass(frozen=True)
class TaskStep:
    """The batch kernel of one task configuration: ``(inputs {name: [n, ...]}, params [P] or [n, P]) ->
    outputs {name: [n, ...]}`` (:func:`_fields` names them), one Pallas call."""

    constants: Constants
    layout: Layout
    block: int | None = None
    interpret: bool | None = None

    def __call__(self, inputs: dict, params: jax.Array) -> dict:
        from jax.experimental import pallas as pl
        from jax.experimental.pallas import triton as plgpu

        ins, outs = _fields(self.layout)
        n = inputs["qpos"].shape[0]
        size = BLOCK if self.block is None else self.block
        size = min(size, max(1, 1 << max(n - 1, 0).bit_length()))
        run_interpreted = jax.default_backend() != "gpu" if self.interpret is None else self.interpret
        compiler = None if run_interpreted else plgpu.CompilerParams(num_warps=max(1, min(8, size // 32)),
                                                                      num_stages=1)
        flat = [jnp.asarray(inputs[name], dtype).reshape(-1) for name, _, dtype in ins]
        whole = pl.BlockSpec(memory_space=pl.ANY)
        shapes = [jax.ShapeDtypeStruct((n * width,), dtype) for _, width, dtype in outs]
        result = pl.pallas_call(
            _kernel(self.constants, self.layout, n, size, params.ndim == 2), grid=(-(-n // size),),
            in_specs=[whole] * (len(ins) + 1), out_specs=[whole] * len(outs), out_shape=shapes,
            interpret=run_interpreted, compiler_params=compiler, name="quadcopter_goto_step",
        )(*flat, params.astype(jnp.float32).reshape(-1))
        return {name: r.reshape((n, width) if width > 1 or name in ("qpos", "qvel", "obs") else (n,))
                for (name, width, _), r in zip(outs, result)}


def make_task_step(env: Any, block: int | None = None, interpret: bool | None = None) -> TaskStep:
    """The batch kernel of ``env`` (a Goto task :func:`supports`; raises ValueError naming why not)."""
    why = supports(env)
    if why is not None:
        raise ValueError(f"no task kernel: {why}")
    o = env.options
    layout = Layout(int(o.n_obstacles), str(o.obstacle_kind), env.step_kernel_variant == "v2", env.randomised)
    return TaskStep(constants_of(env.robot), layout, block, interpret)


# ---- one env's step through the batch kernel ---------------------------------------------------------------
def kernel_step(env: Any, state: Any, action: jax.Array, params: Any) -> Any:
    """``env.step(state, action, params)`` (one env; vmap it) through ``env.step_kernel``: the same
    :class:`jaxrobo.task.env.EnvState` as :meth:`jaxrobo.task.env.TaskEnv.step`, to float32 round-off. A
    randomised task's env brings its drawn domain (``state.domain``, drawn at reset): its physics, in the form
    the robot's XLA step takes (:meth:`envs.quadcopter.robot.Quadcopter.sim_physics`), go into the kernel as
    per-env inputs, and its observation noise is added to the kernel's observation as the XLA step adds it."""
    from jaxrobo.api import EnvState, JointState, randomise, through_batch

    kernel: TaskStep = env.step_kernel
    layout = kernel.layout
    task = state.task
    inputs = {"qpos": state.pipeline_state.qpos, "qvel": state.pipeline_state.qvel,
              "action": jnp.asarray(action, jnp.int32), "obs": state.obs, "goal": task.goal,
              "prev_dist": task.prev_dist, "arrived": task.arrived, "crashed": task.crashed}
    if layout.v2:
        inputs.update(prev_bearing=task.prev_bearing, prev_dz=task.prev_dz)
    if layout.randomised != bool(state.domain):
        raise ValueError(f"the task kernel was built for randomised={layout.randomised}; the state "
                         f"{'carries' if state.domain else 'carries no'} drawn domain")
    if layout.randomised:
        inputs.update(env.robot.sim_physics(randomise.physics_of(state.domain)))
    if layout.n_obstacles:
        obs = task.obstacles
        inputs.update(center=obs.center, size=obs.size, active=obs.active)
        if layout.obstacle_kind == "mixed":
            inputs["kind"] = obs.kind
    p = jnp.stack([jnp.asarray(getattr(params, name), jnp.float32) for name in layout.param_names])
    out = through_batch(kernel, inputs, p)  # one call over the batch; p per env where a sweep batches it
    changes = {name: out[name] for name in ("prev_dist", "arrived", "crashed", "prev_bearing", "prev_dz")
               if name in out}
    terminated = out["terminated"]
    steps = state.steps + 1
    truncated = (steps >= params.max_episode_steps) & ~terminated
    obs = randomise.noisy(out["obs"], state.domain, state.key, steps)  # the identity without a domain
    return EnvState(JointState(out["qpos"], out["qvel"]), obs, out["reward"], terminated, truncated, steps,
                    task.replace(**changes), state.key, out["nan"], domain=state.domain)
