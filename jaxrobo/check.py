"""Check a functional environment the way Gymnasium's ``check_env`` checks a stateful one.

``check_env(env_or_id)`` runs small checks on a jaxrobo env (an id, or an env built by :func:`jaxrobo.make` or by
hand) and returns one :class:`CheckResult` per check; ``jaxrobo check ID [--quick]`` prints them. Each check names
the task hook at fault where it can (``_set_init_pose``, ``_init_env_variables``, ``_set_action``, ``_get_obs``,
``_is_done``, ``_compute_reward``):

* ``spaces``      - a ``Discrete(n>0)`` action space, or a 1-D ``Box`` with finite bounds for a task that declares
  continuous actions (``action_dtype = jnp.float32``; a Box on a task whose ``step`` casts actions to int32 fails),
  an observation ``Box`` of the observation's shape, float32 observations, a float32 scalar reward, bool
  ``terminated``/``truncated``, finite ``state_bounds`` with low < high;
* ``actions``     - every declared action gives ``_set_action`` a command of its own (an ``n`` larger than the task
  handles shows up as two actions with one command); for a Box, moving each action dimension from the middle of
  the Box to its upper bound changes the command (a dimension the task ignores fails);
* ``trace``       - ``reset``/``step`` trace under ``jax.jit`` and ``jax.vmap`` (Python control flow on a traced
  value, or a traced value kept between calls, fails here);
* ``carry``       - a step keeps the state's pytree, every leaf's dtype and shape as reset made them (a task
  variable that turns float, or a scalar that becomes ``(1,)``, would stop every ``lax.scan`` over steps with
  JAX's carry-type error); the failure names the field and the hook that changed it;
* ``pure``        - the same inputs give the same outputs bit for bit, hook by hook, and the input state is left
  as it was;
* ``jit_vmap``    - the jitted and the vmapped calls agree with the plain call;
* ``reset_keys``  - the same key gives the same initial state; different keys different ones where the task's
  reset reads its key (a reset that never reads it is deterministic and passes);
* ``rollout``     - a short random rollout of a few envs: observations finite and inside the observation space,
  finite float rewards, ``truncated`` exactly at ``max_episode_steps`` and never with ``terminated``, and
  ``physics_nan`` only where the physics state is not finite;
* ``nan_guard``   - a non-finite physics state ends the episode (``terminated`` and ``physics_nan``) with a finite
  observation and zero reward;
* ``mjx_native``  - (MJX robots) a few physics steps agree with native MuJoCo from the same states;
* ``gymnasium``   - Gymnasium's own ``check_env`` through the adapter;
* ``long``        - (``long=N``, ``jaxrobo check --long N``) a random rollout of a few envs over ``N`` steps, a fresh
  episode wherever one ends: every float of the state (physics, observation, reward, task variables) stays within
  :data:`HUGE` in magnitude. Finite but huge values (velocities of 1e33 in float32) pass the NaN guard and every
  short rollout, and ruin learning; the failure names the field, the value and the step.

``quick`` shortens the rollout and skips the two checks that build extra models or compiles (``mjx_native``,
``gymnasium``).
"""
from __future__ import annotations

import dataclasses
import traceback
import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core import spaces

#: The task hooks of :class:`jaxrobo.task.env.TaskEnv`, as a traceback names them.
HOOKS = ("_set_init_pose", "_init_env_variables", "_set_action", "_get_obs", "_is_done", "_compute_reward")

OK, FAIL, SKIP = "ok", "FAIL", "skip"

#: The largest magnitude the long rollout accepts in any float of the state: beyond it a simulation has left any
#: range a robot's SI quantities reach (positions in m, velocities in m/s or rad/s, rewards per step).
HUGE = 1e6
#: The longest ``long`` rollout (steps per env).
MAX_LONG = 10_000_000


@dataclasses.dataclass(frozen=True)
class CheckResult:
    name: str
    status: str  # "ok", "FAIL" or "skip"
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.status != FAIL

    def line(self) -> str:
        return f"{self.status:4s} {self.name:11s} {self.message}".rstrip()


class _Fail(Exception):
    """Raised inside a check to report a failure with its message."""


# ---- helpers -------------------------------------------------------------------------------------------------
def _arrays(tree: Any) -> list[np.ndarray]:
    """The leaves of a pytree as numpy copies (key arrays as their key data)."""
    out = []
    for x in jax.tree.leaves(tree):
        if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jax.dtypes.prng_key):
            x = jax.random.key_data(x)
        out.append(np.array(x, copy=True))
    return out


def _same(a: Any, b: Any) -> bool:
    """Bitwise equal pytrees (NaN equal to NaN)."""
    la, lb = _arrays(a), _arrays(b)
    if jax.tree.structure(a) != jax.tree.structure(b) or len(la) != len(lb):
        return False
    return all(x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes() for x, y in zip(la, lb))


def _close(a: Any, b: Any, rtol: float = 1e-5, atol: float = 1e-5) -> bool:
    la, lb = _arrays(a), _arrays(b)
    if len(la) != len(lb):
        return False
    for x, y in zip(la, lb):
        if x.shape != y.shape:
            return False
        if np.issubdtype(x.dtype, np.floating):
            if not np.allclose(x, y, rtol=rtol, atol=atol, equal_nan=True):
                return False
        elif not np.array_equal(x, y):
            return False
    return True


def _hook_in(err: BaseException) -> str | None:
    """The innermost task hook on the traceback of ``err`` (or of the exceptions it chains)."""
    seen = err
    while seen is not None:
        names = [f.name for f in traceback.extract_tb(seen.__traceback__)]
        hooks = [n for n in names if n in HOOKS]
        if hooks:
            return hooks[-1]
        seen = seen.__cause__ or seen.__context__
    return None


def _traced_error(call: str, err: BaseException) -> str:
    hook = _hook_in(err)
    where = f" in {hook}" if hook else ""
    first = str(err).strip().splitlines()[0] if str(err).strip() else ""
    if isinstance(err, jax.errors.UnexpectedTracerError):
        return (f"{call}: a traced value leaked out of a traced call{where} (a hook keeps a traced value between "
                f"calls, e.g. caches its state on self): {type(err).__name__}")
    if isinstance(err, (jax.errors.ConcretizationTypeError, jax.errors.TracerBoolConversionError,
                        jax.errors.TracerIntegerConversionError, jax.errors.TracerArrayConversionError)):
        return (f"{call}: a hook uses Python control flow (or numpy) on a traced value{where}; use jnp.where / "
                f"lax.cond instead: {type(err).__name__}: {first[:160]}")
    return f"{call} raised{where}: {type(err).__name__}: {first[:200]}"


def _state_fields(state: Any) -> dict[str, Any]:
    return {f.name: getattr(state, f.name) for f in dataclasses.fields(state)} if dataclasses.is_dataclass(state) \
        else {}


def _keys(seed: int, n: int) -> jax.Array:
    return jax.random.split(jax.random.key(seed), n)


def _is_task_env(env: Any) -> bool:
    from jaxrobo.task.env import TaskEnv

    return isinstance(env, TaskEnv)


# ---- the checks ----------------------------------------------------------------------------------------------
def _leaf_types(tree: Any) -> tuple[Any, dict[str, str]]:
    """The tree's structure and ``{path: "dtype[shape]"}`` of its leaves (abstract values are fine)."""
    leaves, treedef = jax.tree_util.tree_flatten_with_path(tree)
    types = {}
    for path, leaf in leaves:
        shape = ",".join(str(d) for d in getattr(leaf, "shape", ()))
        types[jax.tree_util.keystr(path).lstrip(".")] = f"{leaf.dtype}[{shape}]"
    return treedef, types


def _type_changes(before: Any, after: Any) -> list[str]:
    """How ``after`` differs from ``before`` in pytree structure, leaf dtypes and shapes (empty: the same types)."""
    tb, lb = _leaf_types(before)
    ta, la = _leaf_types(after)
    changes = [f"{k} changes from {lb[k]} to {la[k]}" for k in lb if k in la and lb[k] != la[k]]
    changes += [f"{k} ({lb[k]}) is gone" for k in lb if k not in la]
    changes += [f"{k} ({la[k]}) appears" for k in la if k not in lb]
    if not changes and tb != ta:
        changes.append(f"the pytree changes from {tb} to {ta}")
    return changes


class _Checker:
    def __init__(self, env: Any, env_id: str | None, params: Any, quick: bool, seed: int, long: int = 0):
        self.env, self.env_id, self.quick, self.seed, self.long = env, env_id, quick, seed, long
        self.params = env.default_params if params is None else params
        self.task = _is_task_env(env)
        # One jitted reset/step and one jitted vmap of each (two envs), shared by the checks: each compiles once.
        self.jreset, self.jstep = jax.jit(env.reset), jax.jit(env.step)
        self.vreset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
        self.vstep = jax.jit(jax.vmap(env.step, in_axes=(0, 0, None)))

    # -- actions of either kind of space (the checks below step with these)
    def _box(self) -> spaces.Box | None:
        act = self.env.action_space(self.params)
        return act if isinstance(act, spaces.Box) else None

    def _action(self, i: int) -> jax.Array:
        """A fixed action ``i``: ``i % n`` of a Discrete space; of a Box, its middle (``i = 0``) or a point a
        quarter of the way from the middle towards the upper (odd ``i``) or lower (even ``i``) bounds."""
        box = self._box()
        if box is None:
            return jnp.int32(i % int(self.env.action_space(self.params).n))
        low, high = np.asarray(box.low, np.float32), np.asarray(box.high, np.float32)
        frac = 0.0 if i == 0 else (0.25 if i % 2 else -0.25)
        return jnp.asarray(0.5 * (low + high) + frac * (high - low), jnp.float32)

    def _actions(self, n: int) -> jax.Array:
        return jnp.stack([self._action(i) for i in range(n)])

    def _random_action(self, key: jax.Array) -> jax.Array:
        box = self._box()
        if box is None:
            return jax.random.randint(key, (), 0, int(self.env.action_space(self.params).n), jnp.int32)
        return jax.random.uniform(key, box.shape, jnp.float32, np.asarray(box.low, np.float32),
                                  np.asarray(box.high, np.float32))

    def _describe_actions(self) -> str:
        act = self.env.action_space(self.params)
        if isinstance(act, spaces.Box):
            return f"Box{act.shape} actions in [{np.min(act.low):g}, {np.max(act.high):g}]"
        return f"Discrete({act.n}) actions"

    # -- spaces
    def spaces(self) -> str:
        env, p = self.env, self.params
        act = env.action_space(p)
        if isinstance(act, spaces.Box):
            dtype = getattr(env, "action_dtype", jnp.int32)
            if not jnp.issubdtype(dtype, jnp.floating):
                raise _Fail(f"action_space() is a Box{act.shape} but step() casts actions to {jnp.dtype(dtype)}: "
                            "declare spaces.Discrete(n), or set action_dtype = jnp.float32 on a task with "
                            "continuous actions")
            low, high = np.asarray(act.low), np.asarray(act.high)
            if low.ndim != 1 or low.shape != high.shape or low.size == 0:
                raise _Fail(f"action_space(): a continuous action Box must be 1-D and non-empty with low and high "
                            f"of one shape, got low {low.shape}, high {high.shape}")
            if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
                raise _Fail(f"action_space(): the action Box needs finite bounds with low < high, got low={low}, "
                            f"high={high}")
        elif not isinstance(act, spaces.Discrete):
            raise _Fail(f"action_space() returned {type(act).__name__}; expected jaxrobo.core.spaces.Discrete(n) or "
                        "jaxrobo.core.spaces.Box")
        elif not isinstance(act.n, (int, np.integer)) or act.n <= 0:
            raise _Fail(f"action_space().n={act.n!r}: expected an integer > 0")
        obs_space = env.observation_space(p)
        if not isinstance(obs_space, spaces.Box):
            raise _Fail(f"observation_space() returned {type(obs_space).__name__}; expected jaxrobo.core.spaces.Box")
        low, high = np.asarray(obs_space.low), np.asarray(obs_space.high)
        if low.shape != high.shape or np.any(low > high):
            raise _Fail(f"observation_space(): low {low.shape} and high {high.shape} must have one shape, low <= high")
        state = env.reset(_keys(self.seed, 1)[0], p)
        hook = "_get_obs" if self.task else "reset"
        obs = state.obs
        if tuple(np.shape(obs)) != tuple(obs_space.shape):
            raise _Fail(f"{hook}: observation shape {tuple(np.shape(obs))} differs from observation_space() "
                        f"shape {obs_space.shape}")
        if obs.dtype != jnp.float32:
            raise _Fail(f"{hook}: observation dtype {obs.dtype}; expected float32 (cast with .astype(jnp.float32))")
        state = env.step(state, self._action(0), p)
        if state.obs.dtype != jnp.float32 or tuple(state.obs.shape) != tuple(obs_space.shape):
            raise _Fail(f"step: observation {state.obs.dtype}{tuple(state.obs.shape)}; expected float32"
                        f"{obs_space.shape}")
        if state.reward.dtype != jnp.float32 or state.reward.shape != ():
            rhook = "_compute_reward" if self.task else "step"
            raise _Fail(f"{rhook}: reward {state.reward.dtype}{tuple(state.reward.shape)}; expected a float32 scalar")
        for name in ("terminated", "truncated", "physics_nan"):
            x = getattr(state, name)
            if x.dtype != jnp.bool_ or x.shape != ():
                dhook = "_is_done" if self.task and name == "terminated" else "step"
                raise _Fail(f"{dhook}: {name} is {x.dtype}{tuple(x.shape)}; expected a bool scalar")
        try:
            blow, bhigh = (np.asarray(b) for b in env.state_bounds(p))
        except NotImplementedError:
            return f"{self._describe_actions()}, float32 obs {obs_space.shape} (no state_bounds)"
        if blow.shape != obs_space.shape or bhigh.shape != obs_space.shape:
            raise _Fail(f"state_bounds(): shapes {blow.shape}/{bhigh.shape}; expected {obs_space.shape} each")
        if not (np.all(np.isfinite(blow)) and np.all(np.isfinite(bhigh)) and np.all(blow < bhigh)):
            raise _Fail(f"state_bounds(): expected finite ranges with low < high, got low={blow}, high={bhigh}")
        return f"{self._describe_actions()}, float32 obs {obs_space.shape}, state_bounds finite"

    # -- every action its own command
    def actions(self) -> str:
        if self._box() is not None:
            return self._box_actions()
        env, p = self.env, self.params
        n = int(env.action_space(p).n)
        state = env.reset(_keys(self.seed, 1)[0], p)
        if self.task:
            outs = [env._set_action(jnp.int32(a), state.task, p) for a in range(n)]
            what = "_set_action gives actions {} and {} the same command and task variables"
        else:
            outs = [env.step(state, jnp.int32(a), p).pipeline_state for a in range(n)]
            what = "step gives actions {} and {} the same next state"
        for i in range(n):
            for j in range(i + 1, n):
                if _same(outs[i], outs[j]):
                    raise _Fail(what.format(i, j) + f": action_space() declares Discrete({n}); does the task "
                                "handle that many actions?")
        return f"{n} actions, {n} distinct commands"

    def _box_actions(self) -> str:
        env, p, box = self.env, self.params, self._box()
        state = env.reset(_keys(self.seed, 1)[0], p)
        middle = self._action(0)
        high = np.asarray(box.high, np.float32)

        def out(a):
            if self.task:
                return env._set_action(jnp.asarray(a, env.action_dtype), state.task, p)
            return env.step(state, a, p).pipeline_state

        base = out(middle)
        hook = "_set_action" if self.task else "step"
        for d in range(box.shape[0]):
            if _same(base, out(middle.at[d].set(high[d]))):
                name = box.names[d] if len(box.names) > d else f"action[{d}]"
                raise _Fail(f"{hook}: moving {name} from the middle of the action Box to its upper bound "
                            f"{high[d]:g} leaves the command unchanged: action_space() declares Box{box.shape}; "
                            "does the task use every dimension?")
        return f"Box{box.shape}: each of the {box.shape[0]} action dimensions changes the command"

    # -- tracing
    def trace(self) -> str:
        env, p = self.env, self.params
        keys = _keys(self.seed, 2)
        try:
            state = self.jreset(keys[0], p)
        except Exception as err:  # noqa: BLE001 - reported with the hook at fault
            raise _Fail(_traced_error("jit(reset)", err)) from err
        try:
            jax.block_until_ready(self.jstep(state, self._action(0), p))
        except Exception as err:  # noqa: BLE001
            raise _Fail(_traced_error("jit(step)", err)) from err
        try:
            states = self.vreset(keys, p)
            jax.block_until_ready(self.vstep(states, jnp.stack([self._action(0)] * 2), p))
        except Exception as err:  # noqa: BLE001
            raise _Fail(_traced_error("vmap(reset/step)", err)) from err
        # Run the plain call after the traced ones: a hook that cached a traced value now leaks it.
        try:
            env.step(env.reset(keys[1], p), self._action(0), p)
        except Exception as err:  # noqa: BLE001
            raise _Fail(_traced_error("reset/step after jit", err)) from err
        return "reset and step trace under jit and vmap"

    # -- the carry's types
    def carry(self) -> str:
        env, p = self.env, self.params
        s0 = jax.eval_shape(lambda k: env.reset(k, p), _keys(self.seed, 1)[0])
        s1 = jax.eval_shape(lambda s, a: env.step(s, a, p), s0, self._action(0))
        changes = _type_changes(s0, s1)
        if not changes:
            return f"a step keeps the state's types ({len(_leaf_types(s0)[1])} leaves)"
        field = changes[0].split(" ", 1)[0]
        hook = self._carry_hook(s0, field)
        raise _Fail(f"{hook}: state.{changes[0]} over a step"
                    f"{' (and ' + str(len(changes) - 1) + ' more)' if len(changes) > 1 else ''}; "
                    "a lax.scan over steps (training, rollouts, evaluation) needs every field to keep the dtype and "
                    "shape reset gave it: cast it (jnp.asarray(x, dtype)) or give it that type in "
                    "_init_env_variables")

    def _carry_hook(self, s0: Any, field: str) -> str:
        """The hook that changed ``field`` of the state (evaluated abstractly, hook by hook, as ``step`` calls them)."""
        if not self.task:
            return "step"
        env, p = self.env, self.params
        if field.startswith("task"):
            action = jnp.asarray(self._action(0), getattr(env, "action_dtype", jnp.int32))
            _, t1 = jax.eval_shape(lambda a, t: env._set_action(a, t, p), action, s0.task)
            if _type_changes(s0.task, t1):
                return "_set_action"
            return "_compute_reward"
        return {"obs": "_get_obs", "terminated": "_is_done", "reward": "_compute_reward"}.get(
            field.split(".")[0].split("[")[0], "step (the robot or its simulator)" if field.startswith("pipeline_state")
            else "step")

    # -- purity
    def pure(self) -> str:
        env, p = self.env, self.params
        key = _keys(self.seed, 1)[0]
        a = self._action(1) if self._box() is not None else jnp.int32(min(1, int(env.action_space(p).n) - 1))
        if self.task:
            self._pure_hooks(key, a)
        s1, s2 = env.reset(key, p), env.reset(key, p)
        if not _same(s1, s2):
            raise _Fail("reset: the same key gave two different states (a hook reads global or numpy random "
                        "state?)")
        before = _arrays(s1)
        n1, n2 = env.step(s1, a, p), env.step(s1, a, p)
        if not _same(n1, n2):
            raise _Fail("step: the same state and action gave two different next states (a hook reads global or "
                        "numpy random state?)")
        after = _arrays(s1)
        if len(before) != len(after) or any(x.tobytes() != y.tobytes() for x, y in zip(before, after)):
            raise _Fail("step modified its input state in place")
        return "same inputs, same outputs (bit for bit); input state untouched"

    def _pure_hooks(self, key: jax.Array, a: jax.Array) -> None:
        env, p = self.env, self.params
        state = env.reset(key, p)
        ps, task = state.pipeline_state, state.task
        obs = env._get_obs(ps, task, p)
        done = env._is_done(obs, ps, task, p)
        calls: list[tuple[str, Callable[[], Any]]] = [
            ("_set_init_pose", lambda: env._set_init_pose(key, p)),
            ("_init_env_variables", lambda: env._init_env_variables(key, ps, p)),
            ("_set_action", lambda: env._set_action(a, task, p)),
            ("_get_obs", lambda: env._get_obs(ps, task, p)),
            ("_is_done", lambda: env._is_done(obs, ps, task, p)),
            ("_compute_reward", lambda: env._compute_reward(obs, done, a, ps, task, p)),
        ]
        for name, call in calls:
            inputs = _arrays((ps, task))
            if not _same(call(), call()):
                raise _Fail(f"{name}: the same inputs gave two different outputs (it reads state from outside its "
                            "arguments: a global counter, numpy random, an attribute it changes)")
            if any(x.tobytes() != y.tobytes() for x, y in zip(inputs, _arrays((ps, task)))):
                raise _Fail(f"{name} modified its input in place")

    # -- jit/vmap agree with the plain call
    def jit_vmap(self) -> str:
        env, p = self.env, self.params
        keys = _keys(self.seed + 1, 2)
        acts = self._actions(2)
        plain = [env.reset(k, p) for k in keys]
        jitted = self.jreset(keys[0], p)
        if not _close(plain[0], jitted):
            raise _Fail("jit(reset) differs from reset (a hook reads Python state that tracing froze?)")
        batch = self.vreset(keys, p)
        for i in range(2):
            if not _close(plain[i], jax.tree.map(lambda x: x[i], batch)):
                raise _Fail(f"vmap(reset) differs from reset for env {i}")
        nplain = [env.step(s, acts[i], p) for i, s in enumerate(plain)]
        if not _close(nplain[0], self.jstep(plain[0], acts[0], p)):
            raise _Fail("jit(step) differs from step (a hook reads Python state that tracing froze?)")
        nbatch = self.vstep(batch, acts, p)
        for i in range(2):
            if not _close(nplain[i], jax.tree.map(lambda x: x[i], nbatch)):
                raise _Fail(f"vmap(step) differs from step for env {i}")
        return "jit and vmap agree with the plain calls"

    # -- keys
    def reset_keys(self) -> str:
        env, p = self.env, self.params
        keys = _keys(self.seed + 2, 4)
        states = [env.reset(k, p) for k in keys]
        if not _same(states[0], env.reset(keys[0], p)):
            raise _Fail("reset: the same key gave two different states (a hook draws from numpy or Python random "
                        "state instead of the key?)")
        # Does the task's reset read its key? Judged on a fresh copy of the env, jitted (one trace, run on every
        # key), so a hook that caches its first result on the env cannot hide it.
        fresh = _fresh(env)
        body = (lambda k: _without_key(fresh.reset(k, p)))
        declared = len({tuple(x.tobytes() for x in _arrays(jax.jit(body)(k))) for k in keys}) > 1
        distinct = len({tuple(x.tobytes() for x in _arrays(_without_key(s))) for s in states})
        if not declared:
            if distinct > 1:
                raise _Fail("reset: different keys gave different states, but a fresh env's jitted reset ignores "
                            "the key (a hook draws from numpy or Python random state?)")
            return "deterministic reset (the hooks do not read the key); same key, same state"
        if distinct < len(keys):
            hook = self._key_hook(keys)
            raise _Fail(f"reset{f' ({hook})' if hook else ''}: {len(keys)} keys gave only {distinct} distinct "
                        "initial states although the task's reset reads its key (a cached state that ignores the "
                        "key?)")
        return f"same key, same state; {len(keys)} keys, {distinct} distinct initial states"

    def _key_hook(self, keys: jax.Array) -> str | None:
        if not self.task:
            return None
        env, p = self.env, self.params
        poses = [env._set_init_pose(k, p) for k in keys]
        if len({tuple(x.tobytes() for x in _arrays(q)) for q in poses}) < len(keys):
            return "_set_init_pose"
        return "_init_env_variables"

    # -- rollout
    def rollout(self) -> str:
        env = self.env
        n_envs, n_steps = (3, 25) if self.quick else (4, 50)
        limit = max(2, n_steps // 2)
        p = self.params.replace(max_episode_steps=limit) if hasattr(self.params, "max_episode_steps") else self.params
        obs_space = env.observation_space(p)
        low, high = np.asarray(obs_space.low, np.float32), np.asarray(obs_space.high, np.float32)

        def one(key):
            k0, k1 = jax.random.split(key)
            s0 = env.reset(k0, p)

            def body(s, k):
                s = env.step(s, self._random_action(k), p)
                finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(s.pipeline_state)
                                            if jnp.issubdtype(x.dtype, jnp.floating)]))
                return s, (s.obs, s.reward, s.terminated, s.truncated, s.physics_nan, s.steps, finite)

            return s0.obs, jax.lax.scan(body, s0, jax.random.split(k1, n_steps))[1]

        obs0, (obs, reward, term, trunc, nan, steps, finite) = jax.tree.map(
            np.asarray, jax.jit(jax.vmap(one))(_keys(self.seed + 3, n_envs)))
        ohook = "_get_obs" if self.task else "reset/step"
        if not np.all(np.isfinite(obs0)):
            raise _Fail(f"{ohook}: reset gave a non-finite observation {obs0[~np.all(np.isfinite(obs0), -1)][0]}")
        # Only the steps of each env's first episode count (step does not reset).
        alive = np.cumsum(term | trunc, axis=1) - (term | trunc) == 0
        if np.any(nan & finite & alive):
            raise _Fail(f"{ohook}: a non-finite observation from a finite physics state (the NaN guard ended the "
                        "episode as physics_nan)")
        if np.any(nan & ~term & alive):
            raise _Fail("step: physics_nan set without terminated")
        ok_obs = alive & ~nan
        if not np.all(np.isfinite(obs[ok_obs])):
            raise _Fail(f"{ohook}: non-finite observation during the rollout")
        allobs = np.concatenate([obs0, obs[ok_obs]])
        out = (allobs < low) | (allobs > high)
        if np.any(out):
            row, dim = np.argwhere(out)[0]
            name = obs_space.names[dim] if len(obs_space.names) > dim else f"obs[{dim}]"
            raise _Fail(f"{ohook}: observation {name}={allobs[row, dim]:.4g} outside observation_space() "
                        f"[{low[dim]:.4g}, {high[dim]:.4g}]")
        if not np.all(np.isfinite(reward[alive])):
            raise _Fail(f"{'_compute_reward' if self.task else 'step'}: non-finite reward during the rollout")
        if np.any(term & trunc):
            raise _Fail("step: terminated and truncated both set on one step")
        want_trunc = (steps >= limit) & ~term
        if np.any((trunc != want_trunc) & alive):
            raise _Fail(f"step: truncated must be set exactly when steps reach max_episode_steps={limit} (and the "
                        "episode did not terminate)")
        return (f"{n_envs} envs x {n_steps} steps (max_episode_steps={limit}): obs finite and in bounds, "
                f"{int(np.sum(term & alive))} terminated, {int(np.sum(trunc & alive))} truncated")

    # -- NaN guard
    def nan_guard(self) -> str:
        env, p = self.env, self.params
        state = env.reset(_keys(self.seed, 1)[0], p)
        ps = jax.tree.map(lambda x: jnp.full_like(x, jnp.nan) if jnp.issubdtype(x.dtype, jnp.floating) else x,
                          state.pipeline_state)
        out = env.step(state.replace(pipeline_state=ps), self._action(0), p)
        if not bool(out.physics_nan) or not bool(out.terminated):
            raise _Fail("step: a non-finite physics state must end the episode with terminated and physics_nan set")
        if bool(out.truncated):
            raise _Fail("step: the NaN guard set truncated; a physics failure is terminated only")
        if not np.all(np.isfinite(np.asarray(out.obs))) or not np.isfinite(float(out.reward)):
            raise _Fail("step: non-finite observation or reward after a non-finite physics state (NaN would reach "
                        "a learner)")
        if float(out.reward) != 0.0:
            raise _Fail(f"step: reward {float(out.reward)} on a physics failure; expected 0")
        return "non-finite physics ends the episode (physics_nan) with a finite observation, reward 0"

    # -- MJX against native MuJoCo
    def mjx_native(self) -> str:
        from jaxrobo.task.env import simulator_of

        sim = simulator_of(self.env)
        if sim is None or getattr(sim, "backend", None) != "mjx":
            return _skip(f"backend {getattr(sim, 'backend', None)!r}: only MJX is compared with native MuJoCo")
        if self.quick:
            return _skip("--quick")
        import mujoco

        env, p = self.env, self.params
        robot = env.robot
        step = jax.jit(sim.physics_step)
        controller = jax.jit(robot.controller)
        state = env.reset(_keys(self.seed + 4, 1)[0], p)
        ps, task, worst = state.pipeline_state, state.task, 0.0
        m = sim.mj_model
        for t in range(3):
            action = jnp.asarray(self._action(t), getattr(env, "action_dtype", jnp.int32))
            command, task = env._set_action(action, task, p)
            for _ in range(min(sim.n_substeps, 4)):
                ctrl = controller(ps, command)
                d = mujoco.MjData(m)
                d.qpos[:], d.qvel[:] = np.asarray(sim.qpos(ps)), np.asarray(sim.qvel(ps))
                d.ctrl[:] = np.asarray(ctrl)
                mujoco.mj_step(m, d)
                ps = step(ps, ctrl)
                err = max(np.abs(np.asarray(sim.qpos(ps)) - d.qpos).max(),
                          np.abs(np.asarray(sim.qvel(ps)) - d.qvel).max())
                worst = max(worst, float(err))
                if err > 1e-4:
                    raise _Fail(f"MJX and native MuJoCo differ by {err:.2e} after one physics step (tolerance 1e-4)")
        return f"MJX matches native MuJoCo step by step (max error {worst:.1e})"

    # -- Gymnasium's checker
    def gymnasium(self) -> str:
        if self.quick:
            return _skip("--quick")
        import gymnasium
        from gymnasium.utils.env_checker import check_env as gym_check_env

        from jaxrobo.interop.gym_adapter import JaxroboEnv
        from jaxrobo.interop.gym_ids import gym_id, register_gymnasium_id
        from jaxrobo.task.registry import registration

        if self.env_id is not None:
            # A user's "module:Id" is registered with Gymnasium under its bare id once its module is imported
            # (make() above imported it); register it here if that registration was missed.
            bare = registration(self.env_id).spec.id
            gid = gym_id(bare)
            if gid not in gymnasium.registry:
                register_gymnasium_id(bare)
            if gid not in gymnasium.registry:
                return _skip(f"{gid} is not registered with Gymnasium (call "
                             "jaxrobo.interop.gym_ids.register_gymnasium_envs() after registering it)")
            genv = gymnasium.make(gid).unwrapped
            what = f"gymnasium.make({gid!r})"
        else:
            genv = JaxroboEnv(env=self.env)
            what = "JaxroboEnv(env=...)"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                gym_check_env(genv, skip_render_check=True)
            except Exception as err:  # noqa: BLE001 - Gymnasium's message is the report
                raise _Fail(f"gymnasium check_env on {what}: {type(err).__name__}: {err}") from err
            finally:
                genv.close()
        notes = sorted({str(w.message).splitlines()[0] for w in caught if "gymnasium" in (w.filename or "")
                        or "env_checker" in str(w.category.__module__)})
        return f"gymnasium check_env passes on {what}" + (f" (warnings: {'; '.join(notes)[:200]})" if notes else "")


    # -- a long rollout: nothing finite but huge
    def long_rollout(self) -> str:
        if not self.long:
            return _skip("jaxrobo check --long N (check_env(long=N)) runs N steps")
        from jaxrobo.task.autoreset import where_done

        env, p, n_envs, n_steps = self.env, self.params, 4, int(self.long)
        probe = jax.eval_shape(lambda k: env.reset(k, p), _keys(self.seed, 1)[0])
        flat, _ = jax.tree_util.tree_flatten_with_path(probe)
        floats = [i for i, (_, leaf) in enumerate(flat) if jnp.issubdtype(leaf.dtype, jnp.floating)]
        paths = [jax.tree_util.keystr(flat[i][0]).lstrip(".") for i in floats]

        def magnitudes(state):
            leaves = jax.tree.leaves(state)
            mags, args = [], []
            for i in floats:
                x = jnp.ravel(leaves[i])
                a = jnp.where(jnp.isfinite(x), jnp.abs(x), 0.0)
                mags.append(jnp.max(a, initial=0.0))
                args.append(jnp.argmax(a) if x.size else jnp.int32(0))
            return jnp.stack(mags), jnp.stack(args).astype(jnp.int32)

        def one(key):
            k0, k1 = jax.random.split(key)
            init = (env.reset(k0, p), jnp.zeros(len(floats)), jnp.full(len(floats), -1, jnp.int32),
                    jnp.zeros(len(floats), jnp.int32), jnp.int32(0), jnp.int32(0))

            def body(carry, k):
                s, worst, first, arg, t, nan_episodes = carry
                ka, kr = jax.random.split(k)
                stepped = env.step(s, self._random_action(ka), p)
                mags, args = magnitudes(stepped)
                first = jnp.where((first < 0) & (mags > HUGE), t, first)
                arg = jnp.where(mags > worst, args, arg)
                worst = jnp.maximum(worst, mags)
                nan_episodes = nan_episodes + stepped.physics_nan.astype(jnp.int32)
                done = stepped.terminated | stepped.truncated
                s = where_done(done, env.reset(kr, p), stepped)
                return (s, worst, first, arg, t + 1, nan_episodes), None

            (_, worst, first, arg, _, nans), _ = jax.lax.scan(body, init, jax.random.split(k1, n_steps))
            return worst, first, arg, nans

        worst, first, arg, nans = jax.tree.map(np.asarray, jax.jit(jax.vmap(one))(_keys(self.seed + 5, n_envs)))
        nan_note = f"; {int(nans.sum())} episodes ended by the NaN guard" if nans.sum() else ""
        if np.any(first >= 0):
            hit = np.where(first >= 0, first, np.iinfo(np.int32).max)
            e, j = np.unravel_index(np.argmin(hit), hit.shape)
            name = self._element_name(paths[j], int(arg[e, j]), flat[floats[j]][1])
            raise _Fail(f"state.{name} passed |x| > {HUGE:.0e} at step {int(first[e, j]) + 1} of env {e} and reached "
                        f"{worst[e, j]:.3g} (random actions, fresh episodes where one ends){nan_note}: "
                        "finite, so the NaN guard "
                        "lets it through; the simulation or the task has left any sane range (a smaller timestep, "
                        "damping, joint limits, clipped velocities or bounded task variables)")
        j = int(np.argmax(worst.max(axis=0))) if len(floats) else 0
        largest = (f"largest |x| {worst.max():.3g} in state.{paths[j]}" if len(floats) else "no float fields")
        return f"{n_envs} envs x {n_steps} steps: every float within {HUGE:.0e} ({largest}){nan_note}"

    def _element_name(self, path: str, index: int, leaf: Any) -> str:
        """``path[i, j]`` of the flat ``index`` in a leaf; an observation's dimension by its name where it has one."""
        shape = tuple(getattr(leaf, "shape", ()))
        if not shape:
            return path
        if path == "obs":
            names = getattr(self.env.observation_space(self.params), "names", ())
            if len(shape) == 1 and index < len(names):
                return f"obs[{index}] ({names[index]})"
        return f"{path}[{', '.join(str(int(i)) for i in np.unravel_index(index, shape))}]"


class _Skip(Exception):
    pass


def _skip(reason: str) -> str:
    raise _Skip(reason)


def _without_key(state: Any) -> Any:
    return {k: v for k, v in _state_fields(state).items() if k != "key"}


def _fresh(env: Any) -> Any:
    """A new env of the same class, options and parameters (a copy if it cannot be rebuilt)."""
    import copy

    try:
        fresh = type(env)(env.options, env.default_params)
        fresh.spec = env.spec
        return fresh
    except Exception:  # noqa: BLE001 - e.g. a wrapper: its own state is what we have
        return copy.copy(env)


#: The checks in the order they run; ``spaces``, ``trace`` or ``carry`` failing stops the rest (they need them).
CHECKS = ("spaces", "actions", "trace", "carry", "pure", "jit_vmap", "reset_keys", "rollout", "nan_guard",
          "mjx_native", "gymnasium", "long")
_PREREQUISITES = ("spaces", "trace", "carry")


def check_env(env_or_id: Any, *, quick: bool = False, seed: int = 0, params: Any = None,
              checks: tuple[str, ...] | None = None, long: int = 0, **overrides: Any) -> list[CheckResult]:
    """Check a jaxrobo env (an id made with ``overrides``, or an env) and return one result per check; ``long``
    steps per env for the ``long`` check (0: it skips).

    Raises :class:`jaxrobo.core.config.ConfigError` for an unknown id or bad overrides (nothing is checked then).
    """
    from jaxrobo.core.config import ConfigError
    from jaxrobo.core.struct import INT32_MAX
    from jaxrobo.task.registry import make

    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= INT32_MAX:
        raise ConfigError(f"seed={seed!r}: expected an integer >= 0 and <= {INT32_MAX}")
    if isinstance(long, bool) or not isinstance(long, int) or not 0 <= long <= MAX_LONG:
        raise ConfigError(f"long={long!r}: expected an integer >= 0 and <= {MAX_LONG} (steps per env)")
    if isinstance(env_or_id, str):
        env_id = env_or_id[len("jaxrobo/"):] if env_or_id.startswith("jaxrobo/") else env_or_id
        if ":" not in env_id:
            from jaxrobo.task.registry import registration

            env_id = registration(env_id).spec.id  # a deprecated name: said once (here), then its id
        env = make(env_id, **overrides)
        env_id = None if overrides else env_id  # Gymnasium's make would build the id's defaults, not these
    else:
        if overrides:
            raise TypeError("overrides apply to an id; pass a made env without them")
        env, env_id = env_or_id, None
    names = CHECKS if checks is None else checks
    unknown = [c for c in names if c not in CHECKS]
    if unknown:
        raise ValueError(f"checks={unknown}: allowed values are {', '.join(CHECKS)}")
    checker = _Checker(env, env_id, params, quick, seed, long)
    results, blocked = [], None
    for name in names:
        if blocked is not None:
            results.append(CheckResult(name, SKIP, f"needs {blocked} to pass"))
            continue
        try:
            results.append(CheckResult(name, OK, getattr(checker, "long_rollout" if name == "long" else name)()))
        except _Skip as why:
            results.append(CheckResult(name, SKIP, str(why)))
        except _Fail as err:
            results.append(CheckResult(name, FAIL, str(err)))
        except Exception as err:  # noqa: BLE001 - a check that cannot run is a failure of the env, reported
            results.append(CheckResult(name, FAIL, _traced_error(name, err)))
        if results[-1].status == FAIL and name in _PREREQUISITES:
            blocked = name
    return results


def format_results(results: list[CheckResult]) -> str:
    return "\n".join(r.line() for r in results)
