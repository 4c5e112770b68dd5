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
``step`` does not reset; :class:`jaxrobo.task.wrappers.AutoReset` and the trainer reset with fresh randomness.
"""
from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import weakref
from typing import Any, ClassVar, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.physics import fused, mjx_lean
from jaxrobo.core import hash_kernel, rng, spaces
from jaxrobo.task import randomise
from jaxrobo.core.precision import check_precision
from jaxrobo.task.robot import Robot
from jaxrobo.core.struct import param, pytree_dataclass
from jaxrobo.task.spec import EnvSpec


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
    #: The episode's randomised physical parameters (:mod:`jaxrobo.task.randomise`), drawn at reset; ``()`` (no
    #: leaves) unless the task's ``randomise`` option is on.
    domain: Any = ()

    @property
    def done(self) -> jax.Array:
        return self.terminated | self.truncated


@pytree_dataclass
class BaseParams:
    """Parameters every task has; tasks extend this with their own (see each task's environment card)."""

    max_episode_steps: int = param(1000, low=1, doc="episode step cap (the seed's timestep_limit)", unit="steps")


@dataclasses.dataclass(frozen=True)
class LearningTarget:
    """What "has learned" means for a task, declared on the task class (:attr:`Env.learning_target`) and read by the
    training summary (:meth:`jaxrobo.training.summary.TrainResult.summary`), so the trainer knows no task's threshold.

    A table reaches the target when its greedy evaluation's ``metric`` is ``>= threshold`` (``better="higher"``, the
    default) or ``<= threshold`` (``better="lower"``: e.g. a minimum-time task's ``mean_length``). ``metric`` is one of
    :data:`TARGET_METRICS`: ``"mean_length"`` / ``"mean_return"`` (mean greedy episode length / return, which the
    trainer's evaluation records per table: the summary gives the share of evaluated tables that reach the target as
    ``eval_share_of_tables_<name>``), or ``"success_rate"`` (share of greedy episodes the task counts as a success: for
    a task whose task variables carry an ``arrived`` flag the evaluation records it too
    (:func:`jaxrobo.training.driver.evaluate_tables`) and the summary adds ``eval_success_rate`` and the share; for any
    other task the summary names the target only and the task measures it itself).
    """

    name: str
    metric: str
    threshold: float
    description: str
    #: Which way the metric improves: ``"higher"`` (default) or ``"lower"``; every "best" the summaries and sweeps
    #: pick (best 100-episode window, best table) follows it (:func:`ranking`).
    better: str = "higher"

    def __post_init__(self) -> None:
        if self.metric not in TARGET_METRICS:
            raise ValueError(f"LearningTarget metric={self.metric!r}: allowed values are {', '.join(TARGET_METRICS)}")
        if self.better not in ("higher", "lower"):
            raise ValueError(f"LearningTarget better={self.better!r}: allowed values are higher, lower")
        if self.better == "lower" and self.metric == "success_rate":
            raise ValueError("LearningTarget better='lower': a success_rate target is reached from above "
                             "(better='lower' is for mean_length or mean_return)")

    def reached(self, score: Any) -> Any:
        """Whether a per-table ``score`` of :attr:`metric` reaches the threshold, in the target's direction."""
        return score >= self.threshold if self.better == "higher" else score <= self.threshold


@dataclasses.dataclass(frozen=True)
class Ranking:
    """What "best" means for a task's figures, from its learning target (:func:`ranking`): one home for the
    choice, read by the run summary, the printed summary and the sweep's metrics.

    ``episode_figure`` (``"return"`` or ``"length"``) is the per-episode record a best 100-episode window is
    taken of, ``table_metric`` (a :data:`TARGET_METRICS` key) the per-table greedy figure the best table is
    chosen by, ``higher`` whether larger values of both are better. A ``success_rate`` target ranks training
    episodes by return (the training records hold no arrivals; a goal task rewards arriving)."""

    episode_figure: str
    table_metric: str
    higher: bool

    @property
    def words(self) -> str:
        """``"return, higher is better"``: what a best figure was chosen by, for a person."""
        return f"{self.episode_figure}, {'higher' if self.higher else 'lower'} is better"

    def best_index(self, scores: Any) -> int:
        """Index of the best of ``scores`` (the first on a tie)."""
        s = np.asarray(scores, np.float64)
        return int(np.argmax(s) if self.higher else np.argmin(s))

    def best_table(self, per_table: dict[str, Any]) -> int:
        """The best evaluated table: ``per_table`` maps :data:`TARGET_METRICS` keys to ``[tables, episodes]``
        greedy records (``mean_return`` at least), chosen by :meth:`best_of`."""
        ret = np.asarray(per_table["mean_return"], np.float64).mean(axis=1)
        score = (np.asarray(per_table[self.table_metric], np.float64).mean(axis=1)
                 if self.table_metric in per_table else None)
        return int(self.best_of(score, ret))

    def best_of(self, score: Any, ret: Any, xp: Any = np) -> Any:
        """Index of the best table from its mean :attr:`table_metric` ``score`` (None: not recorded, so ranked by
        the mean return alone, higher is better), a tie broken by the higher mean return ``ret`` (a success rate
        often ties at 1.0), then the first; a NaN ranks last. One rule for the host's choice (:meth:`best_table`)
        and the traced one among a run's late snapshots (``Trainer.final_table``): ``xp`` is numpy or jax.numpy."""
        last = lambda v: xp.where(v == v, v, -xp.inf)  # noqa: E731  (NaN is the only value unequal to itself)
        ret = last(ret)
        score = ret if score is None else last(score if self.higher else -score)
        return xp.argmax(xp.where(score == score.max(), ret, -xp.inf))


def ranking(target: LearningTarget | None) -> Ranking:
    """The :class:`Ranking` a task's ``learning_target`` implies. Without a target, the seed's: longer episodes
    are better (its tasks are kept going as long as they can)."""
    if target is None:
        return Ranking("length", "mean_length", True)
    higher = target.better == "higher"
    if target.metric == "mean_length":
        return Ranking("length", "mean_length", higher)
    if target.metric == "mean_return":
        return Ranking("return", "mean_return", higher)
    return Ranking("return", "success_rate", higher)


#: The figures a :class:`LearningTarget` can be stated on, each with what it measures (docs/extending.md lists them).
TARGET_METRICS = {
    "mean_length": "mean greedy episode length per evaluated table "
                   "(longer is better, or shorter with better=\"lower\")",
    "mean_return": "mean greedy episode return per evaluated table",
    "success_rate": "share of greedy episodes the task counts as a success (its task variables' `arrived` flag)",
}


class Env:
    """A functional environment. Subclasses declare ``Options`` (static: code paths, shapes, the model) and
    ``Params`` (traced numbers: limits, gains, goals), both dataclasses built with :func:`jaxrobo.core.struct.param`."""

    Options: ClassVar[type]
    Params: ClassVar[type]
    spec: EnvSpec | None = None
    #: What learning this task means (None: the task declares no target, e.g. one that cannot be learned).
    learning_target: ClassVar[LearningTarget | None] = None

    def __init__(self, options: Any = None, params: Any = None):
        # An env built without jaxrobo.make (the task class called directly) meets make's x64 refusal here,
        # before a task's __init__ builds its model.
        check_precision(f"{type(self).__name__}(...)")
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

    def state_bounds(self, params: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Finite per-dimension ranges of the observation that a discretiser should cover: two float32 numpy
        arrays, computed on the host from the parameters' values (never in ``jax.numpy``: each eager operation there
        is a program of its own, which a GPU compiles on first use before the run starts)."""
        raise NotImplementedError

    @property
    def name(self) -> str:
        return self.spec.id if self.spec is not None else type(self).__name__

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name} {self.options}>"


def check_key(key: Any, where: str) -> None:
    """Refuse, naming ``where``, anything but one PRNG key (a typed key of shape ``()`` or a raw ``uint32[2]``);
    only its type and shape are read, so it works on tracers too."""
    dtype, shape = getattr(key, "dtype", None), getattr(key, "shape", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key) and shape == ():
        return
    if dtype is not None and dtype == jnp.uint32 and shape == (2,):
        return
    got = f"{type(key).__name__} {key!r}" if dtype is None else f"an array of {dtype} with shape {shape}"
    hint = " (vmap over a batch of keys)" if dtype is not None and shape not in ((), None) else ""
    raise TypeError(f"{where}: expected one PRNG key such as jax.random.key(seed){hint}, got {got}")


def check_action_shape(space: Any, action: Any, where: str) -> None:
    """Refuse, naming ``where``, an action whose shape does not fit ``space`` (one env's action); shapes are
    known when traced, values are not (see :meth:`TaskEnv.step`)."""
    shape = np.shape(action)
    want = () if isinstance(space, spaces.Discrete) else tuple(getattr(space, "shape", shape))
    if shape != want:
        kind = f"Discrete({space.n}): a scalar" if isinstance(space, spaces.Discrete) else f"shape {want}"
        raise ValueError(f"{where}: action has shape {shape}; one env's action is {kind} (vmap step over envs "
                         "for a batch)")


class TaskEnv(Env):
    """An environment built from a robot and the seed's six task hooks."""

    robot: Robot
    #: The dtype ``step`` casts an action to before ``_set_action``: int32 for a ``Discrete`` task (every built-in
    #: tabular id), float32 for a task declaring a ``spaces.Box`` action space (the continuous ids).
    action_dtype: ClassVar[Any] = jnp.int32
    #: The task's whole step as one batch kernel, where the task offers one (the Goto tasks on the ``rigid``
    #: backend, :mod:`envs.quadcopter.goto_kernel`); None otherwise. Under ``ExecutionPlan(fused="pallas",
    #: task_kernel=True)`` :meth:`step` runs :meth:`_kernel_step` instead of the hooks (:func:`jaxrobo.speed.plan.
    #: task_kernel` reads this attribute), which stay the task's definition the kernel is tested against.
    step_kernel: Any = None
    #: A training chunk of the task with a tabular learner as one kernel, where the task offers one (the analytic
    #: cart-pole with Q-learning, :mod:`envs.cartpole.kernel`); None otherwise. An object with
    #: ``unsupported_run(env, config, agent, discretiser, fused_block)`` (why a run cannot take it; None: it can) and
    #: ``run_chunk(trainer, runner, agent_params, env_params, written)``, which ``ExecutionPlan(fused="pallas")`` runs
    #: in place of the trainer's scanned steps (:func:`jaxrobo.speed.plan.chunk_kernel_refusal`). Read from the
    #: env's class, so a wrapper (whose step the kernel would skip) offers none.
    chunk_kernel: ClassVar[Any] = None
    #: The task's step for one env on the host without JAX, where the task offers one (the cart-pole's,
    #: :mod:`envs.cartpole.host`; the Goto tasks', :mod:`envs.quadcopter.host`); None otherwise. A
    #: :class:`jaxrobo.task.host.HostStep` built as ``host_step(env)``, with ``unsupported(env)`` (why this env
    #: cannot take it; None: it can), ``backends`` (the backends it runs), ``set_params(params)``,
    #: ``start(states, i)`` (an episode from the i-th of a batch of the JAX reset's first states, on the host) and
    #: ``step(action)``; what ``JaxroboEnv(..., engine="numpy")`` steps. Read from the env's class, so a wrapper
    #: (whose step it would skip) offers none.
    host_step: ClassVar[Any] = None

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
    @property
    def randomised(self) -> bool:
        """True when the task draws its physics per episode (its ``randomise`` option,
        :mod:`jaxrobo.task.randomise`)."""
        return bool(getattr(self.options, "randomise", False))

    def reset(self, key: jax.Array, params: Any = None) -> EnvState:
        """A new episode's first state from ``key``, a PRNG key of one env (``jax.random.key(seed)``; vmap
        ``reset`` over split keys for a batch). Anything else is refused when traced (its type and shape are known
        then), naming the argument."""
        check_key(key, f"{type(self).__name__}.reset(key)")
        params = self.default_params if params is None else params
        if _SHARED_RESETS.get() and isinstance(key, jax.core.Tracer):
            # Traced for one of jaxrobo's programs (:func:`shared_resets`): through this env's reset jitted on its
            # own, so that the task's Python is traced once per trace-time choice however many resets the
            # programs hold (the first carry, a chunk's autoreset branches, the greedy flights); XLA inlines the
            # call. Otherwise (called eagerly, or a caller's own jit or vmap) the hooks run inline as they are.
            return self._jitted_reset(trace_choices())(key, params)
        return self._first_state(key, params)

    def _jitted_reset(self, choices: tuple[bool, ...]) -> Any:
        jitted = self.__dict__.setdefault("_jitted_resets", {})
        if choices not in jitted:
            jitted[choices] = jax.jit(self._first_state)
        return jitted[choices]

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "_jitted_resets"}  # made again on first use

    def _first_state(self, key: jax.Array, params: Any) -> EnvState:
        """:meth:`reset`'s state: the seed's hooks composed."""
        # Drawn from the reset key before it is split (folded, not split), so the reset's own draws keep their keys.
        domain = randomise.draw(key, params, self.robot.directional) if self.randomised else ()
        key, pose_key, var_key = rng.split(key, 3)
        qpos, qvel = self._set_init_pose(pose_key, params)
        pipeline_state = self.robot.sim.init(qpos, qvel)
        task = self._init_env_variables(var_key, pipeline_state, params)
        obs = self._get_obs(pipeline_state, task, params)
        false = jnp.zeros((), bool)
        steps = jnp.zeros((), jnp.int32)
        obs = randomise.noisy(obs, domain, key, steps)
        return EnvState(pipeline_state, obs, jnp.zeros((), jnp.float32), false, false, steps, task, key, false,
                        domain=domain)

    def _kernel_step(self, state: EnvState, action: jax.Array, params: Any) -> EnvState:
        """:meth:`step` through :attr:`step_kernel` (one env; a vmapped step makes one call over the batch)."""
        raise NotImplementedError

    def step(self, state: EnvState, action: jax.Array, params: Any = None) -> EnvState:
        """One step of one env (vmap it for a batch): pure, jittable, no Python control flow on ``action``.

        The jit contract: ``action``'s *shape* is checked when traced (a Discrete task takes a scalar, a Box task a
        vector of the space's shape; anything else raises naming the argument), but its *value* cannot be: it
        is cast to :attr:`action_dtype` and used as is. For a ``Discrete(n)`` task an action outside ``0 .. n-1``,
        a NaN or a fraction therefore acts as some other action (a float is truncated, an index out of range is
        clamped by the table lookups) and nothing says so. Code whose actions may be bad wraps the env in
        :class:`jaxrobo.task.wrappers.CheckedActions`: it raises on the host for a concrete bad action and, under
        jit, sets ``state.info["invalid_action"]``. The Gymnasium adapter checks every action on the host."""
        params = self.default_params if params is None else params
        check_action_shape(self.action_space(params), action, f"{type(self).__name__}.step(state, action)")
        action = jnp.asarray(action, self.action_dtype)
        # A task's kernel takes the drawn domain of a randomised task as per-env inputs (the Goto tasks').
        if self.step_kernel is not None and fused.task_kernels():
            return self._kernel_step(state, action, params)
        command, task = self._set_action(action, state.task, params)
        if state.domain:
            pipeline_state = self.robot.advance(state.pipeline_state, command,
                                                domain=randomise.physics_of(state.domain))
        else:
            pipeline_state = self.robot.advance(state.pipeline_state, command)
        ok = self.robot._check_all_systems_ready(pipeline_state)
        obs = self._get_obs(pipeline_state, task, params)
        ok = ok & jnp.all(jnp.isfinite(obs))
        terminated = self._is_done(obs, pipeline_state, task, params)
        reward, task = self._compute_reward(obs, terminated, action, pipeline_state, task, params)
        # A non-finite physics state ends the episode with zero reward, the last finite observation and the task's
        # variables as they were: its outcome (a crash, an arrival) read from NaNs is not defined (comparisons with
        # a NaN are False on XLA, but a kernel's min/max may drop a NaN operand), so it is not taken.
        task = jax.tree.map(lambda new, old: jnp.where(ok, new, old), task, state.task)
        obs = jnp.where(ok, obs, state.obs)
        reward = jnp.where(ok, reward, 0.0).astype(jnp.float32)
        terminated = terminated | ~ok
        steps = state.steps + 1
        truncated = (steps >= params.max_episode_steps) & ~terminated
        # What the agent sees: observation noise (randomised tasks only) after reward and termination, which read
        # the true state.
        obs = randomise.noisy(obs, state.domain, state.key, steps)
        return EnvState(pipeline_state, obs, reward, terminated, truncated, steps, task, state.key, ~ok,
                        domain=state.domain)


#: Whether resets traced now share each env's one trace of its reset (:meth:`TaskEnv.reset`): set while jaxrobo
#: traces its own programs (:meth:`jaxrobo.speed.plan.ExecutionPlan.tracing` enters :func:`shared_resets`).
_SHARED_RESETS: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxrobo_shared_resets", default=False)


@contextlib.contextmanager
def shared_resets() -> Iterator[None]:
    """Within this block (this thread or task), an env's reset traced under jit or vmap is its reset jitted on its
    own, one trace per env and :func:`trace_choices` (a default run's programs traced Goto-v2's reset three times
    in its training chunk alone); the values are those of the hooks traced inline."""
    token = _SHARED_RESETS.set(True)
    try:
        yield
    finally:
        _SHARED_RESETS.reset(token)


def trace_choices() -> tuple[bool, ...]:
    """The trace-time choices in force in this thread or task (what :meth:`jaxrobo.speed.plan.ExecutionPlan.tracing`
    sets: the MJX stage replacement, the fused path's flags, the hash kernel): a program traced under other choices
    is another program, so what is jitted on its own is kept per choice (:meth:`TaskEnv.reset`)."""
    return (mjx_lean.wanted(), fused.unroll_all_substeps(), fused.physics_kernels(), fused.task_kernels(),
            hash_kernel.wanted())


# ---- the layers of a wrapped env ---------------------------------------------------------------------------
#: :func:`reset_shapes` per env object (weakly: an env that is dropped takes its entry with it).
_RESET_SHAPES: "weakref.WeakKeyDictionary[Env, Any]" = weakref.WeakKeyDictionary()


def reset_shapes(env: Env) -> Any:
    """The shapes and dtypes of ``env.reset``'s state under the default parameters (``jax.eval_shape``: nothing
    compiles or runs), traced once per env object: the memory check and the learning-target check both ask, and a
    trace of a task's reset takes tenths of a second."""
    try:
        return _RESET_SHAPES[env]
    except (KeyError, TypeError):  # TypeError: an env that cannot be referenced weakly is traced every time
        pass
    state = jax.eval_shape(env.reset, jax.random.key(0), env.default_params)
    try:
        _RESET_SHAPES[env] = state
    except TypeError:
        pass
    return state


def task_fields(env: Env) -> tuple[str, ...] | None:
    """The fields of ``env``'s task variables as its ``_init_env_variables`` hook declares them (the dataclass its
    return annotation names), without tracing a reset; None where that says nothing certain: a wrapped env (a
    wrapper may change the state), a hook without such an annotation. A learning-target check asks whether the
    task records ``arrived`` before the run starts, and a trace of a task's reset takes tenths of a second."""
    import typing

    if len(layers(env)) != 1:
        return None
    hook = getattr(type(env), "_init_env_variables", None)
    try:
        declared = typing.get_type_hints(hook).get("return") if hook is not None else None
    except Exception:  # noqa: BLE001 - an annotation that does not resolve says nothing
        return None
    if not (isinstance(declared, type) and dataclasses.is_dataclass(declared)):
        return None
    return tuple(f.name for f in dataclasses.fields(declared))


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
