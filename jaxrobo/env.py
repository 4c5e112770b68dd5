"""Functional environments: the task layer with the seed's hooks, over a robot over the sim layer.

``reset(key, params) -> EnvState`` and ``step(state, action, params) -> EnvState`` are pure; the state and the
parameters are pytrees, so both jit and vmap (over environments and over parameters). A task subclass
implements the six hooks of openai_ros' task env as pure functions:

===========================  ====================================================================
hook                         returns
===========================  ====================================================================
``_set_init_pose``           initial ``(qpos, qvel)`` of the robot (may be random)
``_init_env_variables``      the task's per-episode variables (a pytree), fresh at every reset
``_set_action``              the robot command for an action, and updated task variables
``_get_obs``                 the observation vector
``_is_done``                 True when the episode terminates (failure or success)
``_compute_reward``          the reward, and updated task variables
===========================  ====================================================================

``step`` runs them in the seed's order (``_set_action`` → physics → ``_get_obs`` → ``_is_done`` →
``_compute_reward``), then adds the time limit (``truncated``, distinct from ``terminated``) and a guard that
ends the episode, and flags it, if the physics produced a non-finite number, so NaN never reaches a learner.
``step`` does not reset; :class:`jaxrobo.wrappers.AutoReset` and the trainer reset with fresh randomness.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, ClassVar

import jax
import jax.numpy as jnp

from jaxrobo import rng, spaces
from jaxrobo.robot import Robot
from jaxrobo.struct import param, pytree_dataclass


@pytree_dataclass
class EnvState:
    """Everything a step needs; ``task`` holds the task's per-episode variables."""

    pipeline_state: Any
    obs: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    steps: jax.Array
    task: Any
    key: jax.Array
    physics_nan: jax.Array
    info: dict = dataclasses.field(default_factory=dict)

    @property
    def done(self) -> jax.Array:
        return self.terminated | self.truncated


@pytree_dataclass
class BaseParams:
    """Parameters every task has; tasks extend this with their own (see each task's environment card)."""

    max_episode_steps: int = param(1000, low=1, doc="episode step cap (the seed's timestep_limit)", unit="steps")


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """How an environment was registered: id, step limit and the default overrides it was made with."""

    id: str
    #: None in a registration that leaves the step limit to its task's Params default (``jaxrobo.spec`` and
    #: ``make`` fill it in).
    max_episode_steps: int | None
    description: str = ""
    config: str | None = None  # YAML with the env parameters (the seed's split)
    agent_config: str | None = None  # YAML with the learner parameters


@dataclasses.dataclass(frozen=True)
class LearningTarget:
    """What "has learned" means for a task, declared on the task class (:attr:`Env.learning_target`) and read by
    the training summary (:meth:`jaxrobo.train.TrainResult.summary`), so the trainer knows no task's threshold.

    A table reaches the target when its greedy evaluation's ``metric`` is ``>= threshold``. ``metric`` is one of
    :data:`TARGET_METRICS`: ``"mean_length"`` / ``"mean_return"`` (mean greedy episode length / return, which the
    trainer's evaluation records per table: the summary gives the share of evaluated tables that reach the
    target as ``eval_share_of_tables_<name>``), or ``"success_rate"`` (share of greedy episodes the task counts as
    a success; the trainer's evaluation does not record success, so the summary names the target only and the
    task measures it itself).
    """

    name: str
    metric: str
    threshold: float
    description: str

    def __post_init__(self) -> None:
        if self.metric not in TARGET_METRICS:
            raise ValueError(f"LearningTarget metric={self.metric!r}: allowed values are {', '.join(TARGET_METRICS)}")


#: The figures a :class:`LearningTarget` can be stated on.
TARGET_METRICS = ("mean_length", "mean_return", "success_rate")


class Env:
    """A functional environment. Subclasses declare ``Options`` (static: code paths, shapes, the model) and
    ``Params`` (traced numbers: limits, gains, goals), both dataclasses built with :func:`jaxrobo.struct.param`."""

    Options: ClassVar[type]
    Params: ClassVar[type]
    spec: EnvSpec | None = None
    #: What learning this task means (None: the task declares no target, e.g. one that cannot be learned).
    learning_target: ClassVar[LearningTarget | None] = None

    def __init__(self, options: Any = None, params: Any = None):
        self.options = options if options is not None else self.Options()
        self.default_params = params if params is not None else self.Params()

    # ---- interface ------------------------------------------------------------------------------------
    def reset(self, key: jax.Array, params: Any = None) -> EnvState:
        raise NotImplementedError

    def step(self, state: EnvState, action: jax.Array, params: Any = None) -> EnvState:
        raise NotImplementedError

    @property
    def num_actions(self) -> int:
        return self.action_space().n

    def action_space(self, params: Any = None) -> spaces.Discrete:
        raise NotImplementedError

    def observation_space(self, params: Any = None) -> spaces.Box:
        raise NotImplementedError

    @property
    def observation_size(self) -> int:
        return int(self.observation_space().shape[0])

    def state_bounds(self, params: Any = None) -> tuple[jax.Array, jax.Array]:
        """Finite per-dimension ranges of the observation that a discretiser should cover."""
        raise NotImplementedError

    @property
    def name(self) -> str:
        return self.spec.id if self.spec is not None else type(self).__name__

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} {self.options}>"


class TaskEnv(Env):
    """An environment built from a robot and the seed's six task hooks."""

    robot: Robot

    # ---- the seed's hooks (pure; override in tasks) ---------------------------------------------------
    def _set_init_pose(self, key: jax.Array, params: Any) -> tuple[jax.Array, jax.Array]:
        raise NotImplementedError

    def _init_env_variables(self, key: jax.Array, pipeline_state: Any, params: Any) -> Any:
        return ()

    def _set_action(self, action: jax.Array, task: Any, params: Any) -> tuple[jax.Array, Any]:
        raise NotImplementedError

    def _get_obs(self, pipeline_state: Any, task: Any, params: Any) -> jax.Array:
        raise NotImplementedError

    def _is_done(self, obs: jax.Array, pipeline_state: Any, task: Any, params: Any) -> jax.Array:
        raise NotImplementedError

    def _compute_reward(self, obs: jax.Array, done: jax.Array, action: jax.Array, pipeline_state: Any,
                        task: Any, params: Any) -> tuple[jax.Array, Any]:
        raise NotImplementedError

    # ---- composition ----------------------------------------------------------------------------------
    def reset(self, key: jax.Array, params: Any = None) -> EnvState:
        params = self.default_params if params is None else params
        key, pose_key, var_key = rng.split(key, 3)
        qpos, qvel = self._set_init_pose(pose_key, params)
        pipeline_state = self.robot.sim.init(qpos, qvel)
        task = self._init_env_variables(var_key, pipeline_state, params)
        obs = self._get_obs(pipeline_state, task, params)
        false = jnp.zeros((), bool)
        return EnvState(pipeline_state, obs, jnp.zeros((), jnp.float32), false, false, jnp.zeros((), jnp.int32),
                        task, key, false)

    def step(self, state: EnvState, action: jax.Array, params: Any = None) -> EnvState:
        params = self.default_params if params is None else params
        action = jnp.asarray(action, jnp.int32)
        command, task = self._set_action(action, state.task, params)
        pipeline_state = self.robot.advance(state.pipeline_state, command)
        ok = self.robot._check_all_systems_ready(pipeline_state)
        obs = self._get_obs(pipeline_state, task, params)
        ok = ok & jnp.all(jnp.isfinite(obs))
        terminated = self._is_done(obs, pipeline_state, task, params)
        reward, task = self._compute_reward(obs, terminated, action, pipeline_state, task, params)
        # A non-finite physics state ends the episode with zero reward and the last finite observation.
        obs = jnp.where(ok, obs, state.obs)
        reward = jnp.where(ok, reward, 0.0).astype(jnp.float32)
        terminated = terminated | ~ok
        steps = state.steps + 1
        truncated = (steps >= params.max_episode_steps) & ~terminated
        return EnvState(pipeline_state, obs, reward, terminated, truncated, steps, task, state.key, ~ok)


# ---- stepping a batch ------------------------------------------------------------------------------------------
#: Envs that :func:`step_batch` steps together on a GPU when the env runs on MJX; larger batches run as groups
#: of this size one after another (H100, MJX cart-pole with Q-learning, lean MJX, 100-step chunks: at 1,048,576
#: envs 99.9 M env-steps/s as one batch, 110.6 M in groups of 262,144, 109.0 M of 131,072, 104.4 M of 65,536;
#: at 262,144 envs 110.5 M as one batch, 104.4 M in groups of 65,536: benchmarks/results/h100/env_groups.txt).
#: Most likely a step's intermediates fall out of the L2 cache beyond that size (a reading, not profiled).
GPU_ENV_GROUP = 262_144
#: Groups that :func:`map_groups` writes out one after another with static slices (more run in a loop over
#: blocks of this many). Written out, XLA fuses each group's slicing into the code around it and needs no loop
#: (H100, 262,144 cart-poles with Q-learning, stock MJX, in groups of 65,536: 86.1 M env-steps/s in a loop of
#: dynamic slices, 91.4 M written out, same tables); each group written out is one more copy of the step to
#: compile (1,048,576 envs in groups of 262,144, lean MJX: 110.6 M after 51 s of compile with 4 written out,
#: 104.5 M after 12 s with 1).
UNROLLED_GROUPS = 4


def layers(env: Env) -> list[Env]:
    """The env and every env it wraps (wrappers hold theirs in ``.env``), outermost first."""
    out = [env]
    while hasattr(out[-1], "env"):
        out.append(out[-1].env)
    return out


def simulator_of(env: Env) -> Any:
    """The simulator under an env and its wrappers, or None for an env without a robot (e.g. a closed form)."""
    robot = getattr(layers(env)[-1], "robot", None)
    return None if robot is None else robot.sim


def default_env_group(env: Env) -> int | None:
    """How many envs :func:`step_batch` should step at once: :data:`GPU_ENV_GROUP` for MJX on a GPU, otherwise
    None (the whole batch). Not for Brax's pipelines, which ran slower in groups (H100, cart-pole env steps at
    1,048,576 envs, whole batch in session 12 against groups in session 13: generalized 56 -> 33 M/s, spring
    103 -> 92 M/s, positional 51 -> 50 M/s), nor for a closed form (one fused kernel) or a CPU (nothing
    measurable to gain)."""
    sim = simulator_of(env)
    if jax.default_backend() == "gpu" and sim is not None and sim.backend == "mjx":
        return GPU_ENV_GROUP
    return None


def _rows_of(tree: Any) -> int:
    return jax.tree.leaves(tree)[0].shape[0]


def _written_out(fn: Callable[[Any], Any], tree: Any, group: int) -> Any:
    """``fn`` over consecutive static slices of ``group`` rows (the last one shorter if need be), in order."""
    n = _rows_of(tree)
    for start in range(0, n, group):
        rows = slice(start, min(n, start + group))
        part = fn(jax.tree.map(lambda x, rows=rows: x[rows], tree))
        tree = jax.tree.map(lambda x, y, rows=rows: x.at[rows].set(y), tree, part)
    return tree


def map_groups(fn: Callable[[Any], Any], tree: Any, group: int | None, unrolled: int | None = None) -> Any:
    """``fn`` applied to consecutive slices of ``group`` rows of ``tree`` (its leaves share a leading axis), one
    slice after another, each result written back in place; ``fn`` keeps the tree's structure and shapes. With
    ``group`` None or not smaller than the batch, simply ``fn(tree)``. For work whose rows are independent (an
    env step), so the values are those of ``fn(tree)``.

    A batch of up to ``unrolled`` groups (default :data:`UNROLLED_GROUPS`) has them written out with static
    slices; a larger one runs blocks of ``unrolled`` groups in a ``fori_loop`` of dynamic slices and updates,
    then the rows left over written out. In place, not ``lax.map``, whose stacked output would hold the tree
    twice (and which cannot reshape the zero-size leaves of an MJX state's ``act``)."""
    n = _rows_of(tree)
    if group is None or group >= n:
        return fn(tree)
    unrolled = UNROLLED_GROUPS if unrolled is None else unrolled
    if unrolled < 1:
        raise ValueError(f"unrolled={unrolled}: expected an integer >= 1")
    block = group * unrolled  # rows per loop iteration
    if n <= block:
        return _written_out(fn, tree, group)
    n_blocks = n // block

    def one(i, t):
        start = i * block
        part = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, block), t)
        done = _written_out(fn, part, group)
        return jax.tree.map(lambda x, y: jax.lax.dynamic_update_slice_in_dim(x, y, start, 0), t, done)

    tree = jax.lax.fori_loop(0, n_blocks, one, tree)
    head = n_blocks * block
    if head == n:
        return tree
    tail = _written_out(fn, jax.tree.map(lambda x: x[head:], tree), group)
    return jax.tree.map(lambda x, y: x.at[head:].set(y), tree, tail)


def step_batch(env: Env, states: EnvState, actions: jax.Array, params: Any = None,
               group: int | None = None) -> EnvState:
    """``env.step`` over a batch (the leading axis): vmapped over all of it, or with ``group`` set and smaller
    than the batch, vmapped over ``group`` envs at a time (:func:`map_groups`). Each env's step does not depend
    on the others, so the values are the same (bit for bit in the tests and on an H100; XLA may round a last bit
    differently when it compiles the code around the step differently, as at optimisation level 0)."""
    batch = jax.vmap(lambda s, a: env.step(s, a, params))
    return map_groups(lambda sa: (batch(*sa), sa[1]), (states, actions), group)[0]
