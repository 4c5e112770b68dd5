"""Gymnasium adapter: the classic single-env API and a vmapped vector env around any jaxrobo environment.

The seed trained through ``gym.make('CartPoleStayUp-v0')`` one step at a time; this keeps that API for users
and libraries that expect Gymnasium, over the same pure functions the vectorised trainer compiles:

* :class:`JaxroboEnv` - a :class:`gymnasium.Env`: numpy ``float32`` observations, a Python ``float`` reward,
  separate ``terminated`` / ``truncated``, reproducible ``reset(seed=...)``, exact spaces, one jitted call per
  ``step`` and one device→host transfer of its results. ``render_mode="rgb_array"`` draws MuJoCo frames.
  ``engine="numpy"`` steps a task that offers a host step (:attr:`jaxrobo.task.env.TaskEnv.host_step`: the
  cart-pole's) on the host with no JAX call, from the same reset states.
* :class:`JaxroboVectorEnv` - a :class:`gymnasium.vector.VectorEnv` stepping ``num_envs`` copies as one vmapped
  jitted call, numpy batches out, with any of Gymnasium's autoreset modes (``AutoresetMode.NEXT_STEP`` by
  default, ``SAME_STEP`` with ``final_obs``/``final_info``, ``DISABLED`` with ``reset(options={"reset_mask": m})``).

The ids ``jaxrobo/<id>`` that name these classes are registered by :mod:`jaxrobo.interop.gym_ids` on ``import
jaxrobo``, without importing this module (nor JAX) until Gymnasium makes an env.

Seeding: ``reset(seed=s)`` starts from ``env.reset(jax.random.key(s))`` of the functional API (for
``s < 2**32``), so both give the same trajectory; a later ``reset()`` without a seed continues from the key the
previous episode carried (``jax.random.split(state.key)[1]``), as the vector env's autoreset does, so
``JaxroboVectorEnv`` with ``reset(seed=s)`` reproduces Gymnasium's ``SyncVectorEnv`` of single envs seeded
``s, s+1, ...``.

Time limit: the task truncates by itself at its ``max_episode_steps`` parameter, which is also the
``max_episode_steps`` of the Gymnasium registration; ``gymnasium.make`` therefore adds a ``TimeLimit`` at the
same step (both report ``truncated``). ``gymnasium.make(id, max_episode_steps=M)`` can only shorten episodes,
since Gymnasium keeps that keyword for its wrapper; to lengthen them pass
``overrides={"max_episode_steps": M}`` as well.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import gymnasium
import numpy as np
from gymnasium import spaces as gspaces
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from jaxrobo.core import spaces
from jaxrobo.interop.gym_ids import NAMESPACE
from jaxrobo.speed.compiled import CHAIN, N_EXTRA, compiled_for

_KEY_MOD = 2**64  # Gymnasium seeds are any non-negative int; keys hold 64 bits


class InvalidActionError(ValueError, AssertionError):
    """An action the env cannot take; both a ``ValueError`` and the ``AssertionError`` Gymnasium envs raise."""


# ---- action checks (host side, before any JAX call) ----------------------------------------------------------
def check_box_actions(actions: Any, box: gspaces.Box, shape: tuple[int, ...]) -> np.ndarray:
    """Continuous actions of ``shape`` (``box.shape``, with a leading ``num_envs`` axis for a batch) as float32,
    finite and inside ``box``; otherwise :class:`InvalidActionError` naming the first bad entry and the range."""
    try:
        arr = np.asarray(actions, dtype=np.float32)
    except Exception as err:  # noqa: BLE001 - anything numpy cannot read as floats is not an action
        raise InvalidActionError(f"action={actions!r} cannot be read as a float array of shape {shape}") from err
    if arr.shape != shape:
        raise InvalidActionError(f"action has shape {arr.shape}; expected {shape} (a Box{box.shape} action"
                                 + (" per env)" if len(shape) > len(box.shape) else ")"))
    bad = ~np.isfinite(arr) | (arr < box.low) | (arr > box.high)
    if bad.any():
        i = tuple(int(k) for k in np.unravel_index(int(np.argmax(bad)), arr.shape))
        j = i[len(i) - len(box.shape):]
        what = "is not finite" if not np.isfinite(arr[i]) else "is outside the Box"
        raise InvalidActionError(f"action{list(i)}={float(arr[i])!r} {what}: allowed range "
                                 f"[{float(box.low[j])}, {float(box.high[j])}]")
    return arr


def check_action(action: Any, n: int | gspaces.Box) -> np.int32 | np.ndarray:
    """``action`` as an ``int32`` in ``0 .. n-1``, or :class:`InvalidActionError` naming what is wrong; for a
    continuous task ``n`` is its action Box and the action a float32 array inside it."""
    if isinstance(n, gspaces.Box):
        return check_box_actions(action, n, n.shape)
    if isinstance(action, (bool, np.bool_)):
        raise InvalidActionError(f"action={action!r}: a boolean is not an action; expected an integer in [0, {n})")
    if isinstance(action, (int, np.integer)):
        value = int(action)
    else:
        try:
            arr = np.asarray(action)
        except Exception as err:  # noqa: BLE001 - anything numpy cannot read is not an action
            raise InvalidActionError(f"action={action!r} ({type(action).__name__}) is not an integer") from err
        if arr.shape != ():
            raise InvalidActionError(f"action has shape {arr.shape}; a Discrete({n}) action is one integer, shape ()")
        if not np.issubdtype(arr.dtype, np.integer) or arr.dtype == np.bool_:
            what = "NaN" if np.issubdtype(arr.dtype, np.floating) and np.isnan(arr) else f"dtype {arr.dtype}"
            raise InvalidActionError(f"action={action!r} ({what}) is not an integer in [0, {n})")
        value = int(arr)
    if not 0 <= value < n:
        raise InvalidActionError(f"action={value} is out of range: Discrete({n}) takes 0 .. {n - 1}")
    return np.int32(value)


def check_actions(actions: Any, n: int | gspaces.Box, num_envs: int) -> np.ndarray:
    """A batch of actions as ``int32[num_envs]`` in ``0 .. n-1``, or :class:`InvalidActionError`; for a continuous
    task ``n`` is its action Box and the batch ``float32[num_envs, *shape]`` inside it."""
    if isinstance(n, gspaces.Box):
        return check_box_actions(actions, n, (num_envs,) + n.shape)
    try:
        arr = np.asarray(actions)
    except Exception as err:  # noqa: BLE001
        raise InvalidActionError(f"actions={actions!r} cannot be read as an integer array") from err
    if arr.shape != (num_envs,):
        raise InvalidActionError(f"actions have shape {arr.shape}; expected ({num_envs},), one per env")
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
        bad = "NaN" if np.issubdtype(arr.dtype, np.floating) and np.isnan(arr).any() else f"dtype {arr.dtype}"
        raise InvalidActionError(f"actions ({bad}) must be integers in [0, {n})")
    out = (arr < 0) | (arr >= n)
    if out.any():
        i = int(np.argmax(out))
        raise InvalidActionError(f"actions[{i}]={int(arr[i])} is out of range: Discrete({n}) takes 0 .. {n - 1}")
    return arr.astype(np.int32)


# ---- spaces --------------------------------------------------------------------------------------------------
def gym_spaces(env: Any, params: Any = None) -> tuple[gspaces.Discrete | gspaces.Box, gspaces.Box]:
    """The Gymnasium action and observation spaces of a jaxrobo env (Box with the task's own bounds; a continuous
    task's action Box is float32 with its own bounds).

    An unbounded dimension (``±inf`` in the task) becomes ``±float32 max``, as Gymnasium's own CartPole does:
    every finite float32 observation is inside it, and ``check_env`` does not warn about infinite bounds.
    """
    act, obs = env.action_space(params), env.observation_space(params)
    big = np.finfo(np.float32).max
    low = np.nan_to_num(np.asarray(obs.low, np.float32), neginf=-big, posinf=big)
    high = np.nan_to_num(np.asarray(obs.high, np.float32), neginf=-big, posinf=big)
    observation = gspaces.Box(low, high, shape=low.shape, dtype=np.float32)
    if isinstance(act, spaces.Box):
        a_low, a_high = np.asarray(act.low, np.float32), np.asarray(act.high, np.float32)
        return gspaces.Box(a_low, a_high, shape=a_low.shape, dtype=np.float32), observation
    return gspaces.Discrete(int(act.n)), observation


def _action_limit(space: gspaces.Discrete | gspaces.Box) -> int | gspaces.Box:
    """What :func:`check_action` checks against: ``n`` of a Discrete space, the Box itself otherwise."""
    return space if isinstance(space, gspaces.Box) else int(space.n)


def _make_env(env_id: str | None, env: Any, overrides: Mapping[str, Any] | None, kwargs: Mapping[str, Any]) -> Any:
    from jaxrobo.task.registry import make

    values = {**(overrides or {}), **kwargs}
    if env is not None:
        if env_id is not None or values:
            raise TypeError("pass either env= (a made jaxrobo env) or env_id with keyword overrides, not both")
        return env
    if env_id is None:
        raise TypeError("env_id is required (a jaxrobo id such as 'CartPoleStayUp-v0')")
    if env_id.startswith(NAMESPACE + "/"):
        env_id = env_id[len(NAMESPACE) + 1:]
    return make(env_id, **values)


def _reset_params(env: Any, base: Any, options: Mapping[str, Any] | None) -> Any:
    """``options`` may set any task *parameter* for the episodes that follow (e.g. ``init_pole_angle``)."""
    if not options:
        return base
    from jaxrobo.core.config import split_and_validate
    from jaxrobo.core.struct import rules

    static = set(rules(type(env.options))) if hasattr(env, "options") else set()
    bad = sorted(k for k in options if k in static)
    if bad:
        raise ValueError(f"reset options {bad} are static options of {env.name}; pass them to gymnasium.make instead")
    from jaxrobo.core.config import check_relations

    (checked,) = split_and_validate(dict(options), type(base), where=f"{env.name} reset options")
    params = base.replace(**checked)
    check_relations(params, f"{env.name} reset options")
    return params


def _check_seed(seed: Any) -> None:
    """A reset seed is None or an integer >= 0 (Gymnasium's rule); a ValueError naming it otherwise (a string or
    a negative number would otherwise be converted or wrapped silently)."""
    if seed is None:
        return
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed={seed!r}: expected None or an integer >= 0")


def _seed_keys(seeds: Sequence[int]) -> Any:
    """The key of each seed, in one call: ``jax.random.key(s)`` for ``s < 2**32`` (threefry key data is
    ``[s >> 32, s & 0xffffffff]``); larger seeds keep both halves, which ``jax.random.key`` without x64 would not."""
    import jax

    from jaxrobo.core import rng

    return jax.random.wrap_key_data(rng.seed_words([int(x) % _KEY_MOD for x in seeds]))


#: ``JaxroboEnv``'s engines: the task's jitted ``step``, or its host step (:attr:`TaskEnv.host_step`).
ENGINES = ("jax", "numpy")


def _host_step(env: Any, engine: str) -> Any:
    """The host stepper of ``env`` for ``engine="numpy"``, None for ``"jax"``; a ValueError naming the engine and
    why otherwise (a task without a host step, an option the host step does not model)."""
    if engine == "jax":
        return None
    factory = getattr(type(env), "host_step", None)
    if factory is None:
        raise ValueError(f"engine='numpy': {env.name} has no host step (tasks with one: the CartPoleStayUp and "
                         "QuadcopterGoto ids); use engine='jax'")
    why = factory.unsupported(env)
    if why is not None:
        raise ValueError(f"engine='numpy': {env.name}: {why}; use engine='jax'")
    return factory(env)


def _frame_rate(env: Any) -> int:
    from jaxrobo.task.env import simulator_of

    sim = simulator_of(env)
    dt = float(getattr(sim, "running_step", 0.0) or 0.0)
    return max(1, int(round(1.0 / dt))) if dt > 0 else 30


class _Picklable:
    """Stdlib ``pickle`` (what ``multiprocessing`` and SB3's subprocess vector envs use): the compiled functions
    (closures) and the renderer are not pickled but rebuilt on unpickling; an env made from an id is rebuilt from
    the id and its overrides (``_made``), one passed as ``env=`` is pickled as it is. The current state, params and
    random generator go with it, so the copy goes on where the original was."""

    _made: tuple[str, dict[str, Any]] | None = None

    def __getstate__(self) -> dict[str, Any]:
        import jax

        state = dict(self.__dict__)
        state["_fns"] = state["_renderer"] = None
        if "_window" in state:
            state["_window"] = None  # a window belongs to the process that opened it
        if self._made is not None:
            state["jax_env"] = None
        for name in ("state", "states", "params"):
            if state.get(name) is not None:
                state[name] = jax.device_get(state[name])
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        if self.jax_env is None:
            env_id, values = self._made
            self.jax_env = _make_env(env_id, None, values, {})
        self._fns = self._compile()


# ---- the single environment ----------------------------------------------------------------------------------
class JaxroboEnv(_Picklable, gymnasium.Env):
    """A jaxrobo env with Gymnasium's classic single-env API.

    ``JaxroboEnv("CartPoleStayUp-v0", control_type="position")`` or ``gymnasium.make("jaxrobo/CartPoleStayUp-v0",
    control_type="position")``: keyword arguments are the same overrides :func:`jaxrobo.make` takes;
    ``overrides={...}`` passes them as a dict (for names Gymnasium keeps for itself, like ``max_episode_steps``).

    ``engine``: ``"jax"`` (default) steps the task's jitted ``step``; ``"numpy"`` steps the task's host step
    (:attr:`jaxrobo.task.env.TaskEnv.host_step`, float64 on the host, no JAX call; resets still draw the first
    state through the jitted reset, so a seed gives the same episode within float32 rounding). A task without
    one is refused here.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 25}

    def __init__(self, env_id: str | None = None, render_mode: str | None = None, *, env: Any = None,
                 overrides: Mapping[str, Any] | None = None, width: int = 320, height: int = 240,
                 camera: str | int | None = None, engine: str = "jax", **kwargs: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r}: allowed values are None, "
                             + ", ".join(repr(m) for m in self.metadata["render_modes"]))
        if engine not in ENGINES:  # before the env is built
            raise ValueError(f"engine={engine!r}: allowed values are {', '.join(map(repr, ENGINES))}")
        from jaxrobo.pictures import window
        from jaxrobo.pictures.render import check_frame_size

        width, height = check_frame_size(width, height, "JaxroboEnv")  # at make, not at the first render()
        no_window = window.unavailable_reason()
        if render_mode == "human" and no_window is not None:  # refused now, with the reason, not at render()
            raise gymnasium.error.DependencyNotInstalled(f"render_mode='human': {no_window}")
        self.jax_env = _make_env(env_id, env, overrides, kwargs)
        self._made = None if env is not None else (env_id, {**(overrides or {}), **kwargs})
        self.params = self.jax_env.default_params
        self.action_space, self.observation_space = gym_spaces(self.jax_env, self.params)
        self._n = _action_limit(self.action_space)
        self._obs_size = int(np.prod(self.observation_space.shape))
        self.engine = engine
        self._host = _host_step(self.jax_env, engine)  # the host stepper (engine="numpy"), else None
        self._chain: Any = None  # engine="numpy": the reset chain (see _host_reset)
        self._fns = self._compile()
        self.render_mode = render_mode
        # The modes this env can render here: "human" only where a window can open (Gymnasium's check_env makes
        # the env once per declared mode; a headless machine then checks rgb_array alone).
        self.metadata = {**type(self).metadata, "render_fps": _frame_rate(self.jax_env),
                         "render_modes": ["rgb_array"] if no_window else ["human", "rgb_array"]}
        self._render_args = (int(width), int(height), camera)
        self._renderer: Any = None
        self._window: Any = None  # render_mode="human": jaxrobo.pictures.window.Window
        self.state: Any = None  # the current jaxrobo EnvState (on device); engine="numpy": the host step holds it

    def _compile(self) -> Any:
        return compiled_for(self.jax_env)

    # -- core API ----------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``seed`` gives the functional ``reset(jax.random.key(seed))``; ``options`` may set task
        parameters (``{"init_pole_angle": 0.52}``) for this and later episodes."""
        super().reset(seed=seed)
        params = _reset_params(self.jax_env, self.params, options)
        changed, self.params = params is not self.params, params
        if self._host is not None:
            obs = self._host_reset(seed, changed)
        else:
            obs = self._jax_reset(seed)
        if self.render_mode == "human":  # Gymnasium's convention: a human-mode env draws itself
            self.render()
        return obs, {}

    def _jax_reset(self, seed: int | None) -> np.ndarray:
        if seed is not None:
            key = _seed_keys([seed])[0]
        elif self.state is not None:
            key = self._fns.next_key(self.state.key)
        else:
            key = _seed_keys([int(self.np_random.integers(2**32))])[0]
        self.state, packed = self._fns.reset(key, self.params)
        obs, *_ = self._unpack(np.asarray(packed))
        return obs

    def _host_reset(self, seed: int | None, changed: bool) -> np.ndarray:
        """The next episode of a host-stepped env: its first state from the reset chain (``reset_chain``: one
        jitted call per :data:`~jaxrobo.speed.compiled.CHAIN` episodes, each starting from the key the same rule
        as :meth:`_jax_reset` gives), continued while no seed or new parameters break it."""
        import jax

        chain = self._chain  # (first states [CHAIN] with key data, key data [CHAIN + 1, 2], current episode)
        if seed is None and chain is not None and not changed and chain[2] + 1 < CHAIN:
            chain = (chain[0], chain[1], chain[2] + 1)
        else:
            if seed is not None:
                key = _seed_keys([seed])[0]
            elif chain is not None:
                key = jax.random.wrap_key_data(chain[1][chain[2] + 1])
            else:
                key = _seed_keys([int(self.np_random.integers(2**32))])[0]
            states, data = self._fns.reset_chain(key, self.params)
            chain = (jax.device_get(states), np.asarray(data), 0)
            self._host.set_params(self.params)
        self._chain = chain
        return self._host.start(chain[0], chain[2]).reshape(self.observation_space.shape)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self.state is None and self._chain is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = check_action(action, self._n)
        if self._host is not None:
            obs, reward, terminated, truncated, nan, steps = self._host.step(int(a))
        else:
            self.state, packed = self._fns.step(self.state, a, self.params)
            obs, reward, terminated, truncated, nan, steps = self._unpack(np.asarray(packed))
        if self.render_mode == "human":
            self.render()
        return obs, reward, terminated, truncated, {"steps": steps, "physics_nan": nan}

    def _unpack(self, row: np.ndarray) -> tuple[np.ndarray, float, bool, bool, bool, int]:
        d = self._obs_size
        obs = row[:d].reshape(self.observation_space.shape)
        reward, term, trunc, nan, steps = row[d:d + N_EXTRA]
        return obs, float(reward), bool(term), bool(trunc), bool(nan), int(steps)

    # -- rendering ---------------------------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """An ``H x W x 3`` uint8 frame of the current state in ``rgb_array`` mode; in ``human`` mode the frame is
        shown in a window at ``metadata["render_fps"]`` (reset and step draw it themselves) and None returned;
        None without a render mode."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' to make")
            return None
        if self.state is None and self._chain is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        if self._renderer is None:
            from jaxrobo.pictures.render import Renderer

            self._renderer = Renderer(self.jax_env, *self._render_args)
        state = self.state
        if self._host is not None:  # the episode's first state with the host's current pose
            import dataclasses

            import jax

            from jaxrobo.physics.sim import JointState

            first = jax.tree.map(lambda x: x[self._chain[2]], self._chain[0])
            state = dataclasses.replace(first, pipeline_state=JointState(*self._host.joints()))
        frame = self._renderer.render(state, self.params)
        if self.render_mode != "human":
            return frame
        if self._window is None:
            from jaxrobo.pictures.window import Window

            self._window = Window(f"jaxrobo {self.jax_env.name}", self.metadata["render_fps"])
        self._window.show(frame)
        return None

    def close(self) -> None:
        if self._window is not None:
            self._window.close()
            self._window = None
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()

    def __repr__(self) -> str:
        engine = "" if self._host is None else f" engine={self.engine}"
        return f"<JaxroboEnv {self.jax_env.name}{engine}>"


# ---- the vector environment ----------------------------------------------------------------------------------
def autoreset_mode_of(value: Any) -> AutoresetMode:
    """``value`` as an :class:`AutoresetMode`: the enum, its value (``"NextStep"``, as ``SyncVectorEnv`` takes) or its
    name (``"NEXT_STEP"``); anything else is a ``ValueError`` naming the allowed values."""
    if isinstance(value, AutoresetMode):
        return value
    if isinstance(value, str):
        for mode in AutoresetMode:
            if value in (mode.value, mode.name):
                return mode
    allowed = ", ".join(f"AutoresetMode.{m.name} (or {m.value!r})" for m in AutoresetMode)
    raise ValueError(f"autoreset_mode={value!r}: allowed values are {allowed}")


def _check_reset_mask(mask: Any, num_envs: int) -> np.ndarray:
    """The ``reset_mask`` option as ``bool[num_envs]`` with at least one True (Gymnasium's own conditions), or a
    ``ValueError`` naming what is wrong."""
    arr = np.asarray(mask)
    if arr.dtype != np.bool_:
        raise ValueError(f"reset_mask has dtype {arr.dtype}; expected a boolean array of shape ({num_envs},)")
    if arr.shape != (num_envs,):
        raise ValueError(f"reset_mask has shape {arr.shape}; expected ({num_envs},), one flag per env")
    if not arr.any():
        raise ValueError("reset_mask selects no env; it needs at least one True (skip the reset instead)")
    return arr


class JaxroboVectorEnv(_Picklable, gymnasium.vector.VectorEnv):
    """``num_envs`` copies of a jaxrobo env stepped as one vmapped jitted call, with Gymnasium's autoreset modes.

    ``autoreset_mode`` (``metadata["autoreset_mode"]``; the enum or its string value, as ``SyncVectorEnv`` takes):

    * ``AutoresetMode.NEXT_STEP`` (default, as ``SyncVectorEnv``'s): after a step that ends an env's episode
      (terminated or truncated), the next ``step`` resets that env and returns its first observation with reward 0,
      ``terminated=truncated=False``, ignoring its action. ``info`` holds ``steps`` and ``physics_nan`` with their
      ``_steps`` / ``_physics_nan`` masks (False for envs that were reset on this step).
    * ``AutoresetMode.SAME_STEP``: a step that ends an env's episode also resets it; it returns that step's reward
      and flags with the next episode's first observation, and the final observation and info in
      ``info["final_obs"]`` (an object array, None for the other envs) and ``info["final_info"]``, with the
      ``_final_obs`` / ``_final_info`` masks (both keys only on steps where some env finished). ``steps`` and
      ``physics_nan`` are masked out for the envs that were reset.
    * ``AutoresetMode.DISABLED``: envs never reset by themselves; ``reset(options={"reset_mask": mask})`` resets the
      envs where ``mask`` is True and keeps the others. Stepping a batch that holds a finished env raises
      :class:`gymnasium.error.ResetNeeded`.

    In every mode the step, and the resets it does, are one jitted call; a reset starts from fresh randomness: the
    key the env's state carries (or the seed's key), never a cached first state. ``reset_mask`` works in every mode.

    ``plan``: a :class:`jaxrobo.speed.plan.ExecutionPlan` for how the batch is stepped and compiled (default: the plan
    for this env on the default device); it changes the compiled program, never the values.

    ``engine``: ``"jax"`` only (the batch is one vmapped call). Host-stepped envs are Gymnasium's own vector env of
    single envs: ``gymnasium.make_vec(id, n, vectorization_mode="sync", engine="numpy")``.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(self, env_id: str | None = None, num_envs: int = 1, render_mode: str | None = None, *,
                 env: Any = None, overrides: Mapping[str, Any] | None = None, width: int = 320, height: int = 240,
                 camera: str | int | None = None, plan: Any = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, engine: str = "jax", **kwargs: Any):
        if engine not in ENGINES:
            raise ValueError(f"engine={engine!r}: allowed values are {', '.join(map(repr, ENGINES))}")
        if engine != "jax":
            raise ValueError(f"engine={engine!r}: a JaxroboVectorEnv steps its envs as one vmapped JAX call; for "
                             "host-stepped envs pass vectorization_mode='sync' to gymnasium.make_vec (one "
                             f"JaxroboEnv(engine={engine!r}) per env)")
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r}: expected an integer >= 1")
        self.autoreset_mode = autoreset_mode_of(autoreset_mode)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r}: allowed values are None, 'rgb_array' (a vector env "
                             "draws no window; render_mode='human' is the single env's)")
        from jaxrobo.pictures.render import check_frame_size

        width, height = check_frame_size(width, height, "JaxroboVectorEnv")  # at make, not at the first render()
        self.jax_env = _make_env(env_id, env, overrides, kwargs)
        self._made = None if env is not None else (env_id, {**(overrides or {}), **kwargs})
        self.params = self.jax_env.default_params
        self.num_envs = int(num_envs)
        self.single_action_space, self.single_observation_space = gym_spaces(self.jax_env, self.params)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._n = _action_limit(self.single_action_space)
        self._obs_size = int(np.prod(self.single_observation_space.shape))
        from jaxrobo.speed.plan import ExecutionPlan

        #: How the batch is stepped (:class:`jaxrobo.speed.plan.ExecutionPlan`; default: the plan for this env on the
        #: default device, which steps large MJX batches on a GPU in groups, as the trainer does).
        self.plan = ExecutionPlan.for_run(self.jax_env) if plan is None else plan
        self._fns = self._compile()
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": _frame_rate(self.jax_env),
                         "autoreset_mode": self.autoreset_mode}
        self._render_args = (int(width), int(height), camera)
        self._renderer: Any = None
        self.states: Any = None
        self._needs_reset: Any = None
        self._done = np.zeros(self.num_envs, bool)  # envs whose episode ended on the last step (host copy)

    def _compile(self) -> Any:
        return compiled_for(self.jax_env, self.plan)

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every env; ``seed=s`` seeds env ``i`` with ``s + i`` (as ``SyncVectorEnv`` does), a list seeds each.

        ``options={"reset_mask": mask}`` (``bool[num_envs]``, as Gymnasium's vector envs take it) resets only the
        envs where ``mask`` is True, from their seed if one is given, else from the key their state carries; the
        others keep their state and observation."""
        for s in (seed if isinstance(seed, (list, tuple)) else [seed]):
            _check_seed(s)
        if options and "reset_mask" in options:
            rest = {k: v for k, v in options.items() if k != "reset_mask"}
            return self._reset_where(_check_reset_mask(options["reset_mask"], self.num_envs), seed, rest)
        if isinstance(seed, (list, tuple)):
            if len(seed) != self.num_envs:
                raise ValueError(f"{len(seed)} seeds for {self.num_envs} envs")
            seeds = list(seed)
            super().reset(seed=None)
        else:
            super().reset(seed=seed)
            seeds = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        self.params = _reset_params(self.jax_env, self.params, options)
        if self.states is not None and all(s is None for s in seeds):
            keys = self._fns.vnext_key(self.states.key)  # continue each env's own key chain
        else:
            seeds = [int(self.np_random.integers(2**32)) if s is None else int(s) for s in seeds]
            keys = _seed_keys(seeds)
        self.states, self._needs_reset, packed = self._fns.vreset(keys, self.params)
        self._done = np.zeros(self.num_envs, bool)
        obs, *_ = self._unpack(np.asarray(packed))
        return obs, {}

    def _reset_where(self, mask: np.ndarray, seed: int | Sequence[int | None] | None, options: dict[str, Any]
                     ) -> tuple[np.ndarray, dict[str, Any]]:
        if self.states is None:
            raise gymnasium.error.ResetNeeded("reset(options={'reset_mask': ...}) resets some envs of a running "
                                              "batch: call reset() without a mask first")
        if options:
            raise ValueError(f"reset options {sorted(options)} given with reset_mask: task parameters are shared by "
                             "every env of the batch; set them in a reset() without reset_mask")
        if isinstance(seed, (list, tuple)):
            if len(seed) != self.num_envs:
                raise ValueError(f"{len(seed)} seeds for {self.num_envs} envs")
            seeds = list(seed)
        else:
            seeds = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        seeded = np.array([s is not None for s in seeds])
        keys = _seed_keys([0 if s is None else int(s) for s in seeds])
        self.states, self._needs_reset, packed = self._fns.vreset_where(
            self.states, self._needs_reset, mask, seeded, keys, self.params)
        self._done = self._done & ~mask
        obs, *_ = self._unpack(np.asarray(packed))
        return obs, {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self.states is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = check_actions(actions, self._n, self.num_envs)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            return self._step_same(a)
        if self.autoreset_mode == AutoresetMode.DISABLED:
            return self._step_disabled(a)
        self.states, self._needs_reset, packed = self._fns.vstep(self.states, self._needs_reset, a, self.params)
        obs, rewards, terms, truncs, nan, steps = self._unpack(np.asarray(packed))
        was_reset = steps == 0
        info = {"steps": np.where(was_reset, 0, steps).astype(np.int64), "_steps": ~was_reset,
                "physics_nan": nan & ~was_reset, "_physics_nan": ~was_reset}
        return obs, rewards, terms, truncs, info

    def _step_same(self, a: np.ndarray):
        self.states, packed = self._fns.vstep_same(self.states, a, self.params)
        rows = np.asarray(packed)
        final, rewards, terms, truncs, nan, steps = self._unpack(rows)
        obs = rows[:, self._obs_size + N_EXTRA:].reshape(final.shape)
        done = terms | truncs
        info: dict[str, Any] = {"steps": np.where(done, 0, steps), "_steps": ~done,
                                "physics_nan": nan & ~done, "_physics_nan": ~done}
        if done.any():
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(done):
                final_obs[i] = final[i]
            info["final_obs"], info["_final_obs"] = final_obs, done
            info["final_info"] = {"steps": np.where(done, steps, 0), "_steps": done.copy(),
                                  "physics_nan": nan & done, "_physics_nan": done.copy()}
            info["_final_info"] = done.copy()
        return obs, rewards, terms, truncs, info

    def _step_disabled(self, a: np.ndarray):
        if self._done.any():
            raise gymnasium.error.ResetNeeded(
                f"envs {np.flatnonzero(self._done).tolist()} finished their episodes and autoreset_mode is DISABLED:"
                " reset them with reset(options={'reset_mask': mask}) before the next step")
        self.states, packed = self._fns.vstep_plain(self.states, a, self.params)
        obs, rewards, terms, truncs, nan, steps = self._unpack(np.asarray(packed))
        self._done = terms | truncs
        every = np.ones(self.num_envs, bool)
        return obs, rewards, terms, truncs, {"steps": steps, "_steps": every, "physics_nan": nan,
                                             "_physics_nan": every.copy()}

    def _unpack(self, rows: np.ndarray):
        d = self._obs_size
        obs = rows[:, :d].reshape((self.num_envs,) + self.single_observation_space.shape)
        extra = rows[:, d:d + N_EXTRA]
        return (obs, extra[:, 0].astype(np.float64), extra[:, 1] > 0.5, extra[:, 2] > 0.5, extra[:, 3] > 0.5,
                extra[:, 4].astype(np.int64))

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One ``H x W x 3`` uint8 frame per env (``rgb_array`` mode), as ``SyncVectorEnv`` returns them."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        if self.states is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        import jax

        if self._renderer is None:
            from jaxrobo.pictures.render import Renderer

            self._renderer = Renderer(self.jax_env, *self._render_args)
        host = jax.device_get(self.states)
        return tuple(self._renderer.render(jax.tree.map(lambda x, i=i: x[i], host), self.params)
                     for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __repr__(self) -> str:
        mode = "" if self.autoreset_mode == AutoresetMode.NEXT_STEP else f" {self.autoreset_mode.name}"
        return f"<JaxroboVectorEnv {self.jax_env.name} x{self.num_envs}{mode}>"
