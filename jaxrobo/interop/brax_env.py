"""Brax's ``Env`` interface over any jaxrobo env with a continuous (``Box``) action space, so Brax's maintained
trainers (``brax.training.agents.ppo.train``, ``sac.train``) run unchanged on jaxrobo tasks.

>>> from brax.training.agents.ppo import train as ppo
>>> from jaxrobo.interop import brax_env
>>> env = brax_env.make("CartPoleContinuous-v0")
>>> make_policy, params, metrics = ppo.train(env, num_timesteps=..., episode_length=1000,
...                                          wrap_env_fn=brax_env.wrap_for_training)

Public surface:

:class:`BraxEnv` ``(env, params=None)``
    One env, Brax's way: ``reset(rng)``, ``step(state, action)``, ``observation_size``, ``action_size``,
    ``backend``. ``rng`` is a raw ``uint32[2]`` key (what Brax's trainers pass) or a typed JAX key. The Brax
    ``State`` carries the whole jaxrobo :class:`jaxrobo.task.env.EnvState` as its ``pipeline_state`` (physics state,
    task variables, step count and the env's own key), and:

    * ``obs``: the raw float32 observation (never discretised); ``reward``: float32;
    * ``done``: float32, 1 on termination or truncation (Brax's trainers take ``discount = 1 - done``);
    * ``info['truncation']``: 1 where the episode hit its step limit without terminating, 0 on termination
      (Brax's PPO and SAC mask truncated transitions out of bootstrapping); ``info['time_out']`` the same
      (read by PPO's ``bootstrap_on_timeout``); the step count is ``pipeline_state.steps`` (``info['steps']``
      belongs to the training wrapper, as in Brax, where its ``EpisodeWrapper`` keeps it);
    * ``metrics``: ``terminated``, ``truncated``, ``physics_nan`` (per step, 0/1) and whatever the task's
      optional ``step_metrics(state, params)`` adds (e.g. ``arrived`` for the Goto Twist task), each a float32
      whose sum over an episode means something: Brax's evaluator reports it as ``eval/episode_<name>``.

    Actions are in [-1, 1] per dimension (Brax's policies squash with tanh) and are mapped affinely onto the
    task's ``Box`` bounds (the identity for the built-in continuous ids, whose Box is [-1, 1]). A task with a
    ``Discrete`` action space is refused, naming the continuous id of the same robot and task where one is
    registered: a Gaussian policy's real vector has no faithful meaning as one of a few discrete commands.
    ``BraxEnv.step`` does not reset: as for Brax's own envs, resetting is the training wrapper's job.
:func:`make` ``(env_id, **overrides)``
    ``BraxEnv(jaxrobo.make(env_id, **overrides))``; ``env_id`` may be ``"module:Id"`` (a user's task).
:func:`wrap_for_training` ``(env, episode_length=1000, action_repeat=1, randomization_fn=None)``
    What ``ppo.train(..., wrap_env_fn=wrap_for_training)`` and ``sac.train`` call in place of
    ``brax.envs.training.wrap``: a batched env (``reset`` takes ``[n, 2]`` keys) with

    * **fresh auto-resets**: a done env starts its next episode from ``env.reset`` with a new key split from
      its own carried key (:func:`jaxrobo.task.autoreset.autoreset`), never Brax's ``AutoResetWrapper``, which
      returns every episode after the first to one cached first state;
    * the step limit ``episode_length`` (env steps, as Brax counts them) in place of the env's own
      ``max_episode_steps``, so truncation (``info['truncation']``) and the trainer's evaluation agree;
    * ``action_repeat`` env steps per call, rewards summed, stopping at the first done step (Brax's
      ``EpisodeWrapper`` keeps stepping a finished episode);
    * ``info['steps']``: the episode's step count (float32, as Brax's ``EpisodeWrapper`` keeps it; its
      evaluator reads it);
    * the returned state of a finished step carries that step's ``reward``, ``done``, ``truncation``,
      ``steps`` and ``metrics``, and the next episode's first ``obs`` (Brax's convention: ``next_observation``
      of a done transition is the new episode's; PPO and SAC never bootstrap through it);
    * ``info['episode_metrics']`` (``sum_reward``, ``length`` and each metric summed over the running
      episode) and ``info['episode_done']``, which Brax's PPO reads when it logs training metrics.

    ``randomization_fn`` (Brax's domain randomisation edits a Brax ``System``) is refused: a jaxrobo env has
    no ``System``; vary its ``Params`` instead (``BraxEnv(env, params)``).

:func:`install_jax_compat` ``()``
    Brax 0.14's trainers call ``jax.device_put_replicated`` / ``device_put_sharded``, which JAX 0.10 removed;
    importing this module installs JAX's documented replacements where they are missing, so ``ppo.train`` and
    ``sac.train`` run unchanged. It lives, version-guarded, in :mod:`jaxrobo.interop.brax_compat`.

MuJoCo Playground (optional extra ``playground``): its ``wrapper.wrap_for_brax_training`` drives a BraxEnv too
(the states answer to Playground's ``state.data``), but train with :func:`wrap_for_training`: Playground's default
(``full_reset=False``) returns to a cached first state, as Brax's wrapper does, and ``full_reset=True`` draws fresh
episodes but resets ``info`` with the state on the done step, so a time-limit step reaches the trainer with
``info['truncation'] = 0`` and is bootstrapped as a termination.

Why Brax's ``wrap_env_fn=None`` path must not be used: ``brax.envs.training.wrap`` adds ``AutoResetWrapper``
(the cached first state above; every training episode would start from the same goal and obstacle), and its
``EpisodeWrapper`` counts steps beside the env's own and rewrites ``info['truncation']`` from its count alone, so
an episode the env truncates at its own ``max_episode_steps`` reaches the trainer as a termination.
``tests/test_brax_env.py`` shows the cached state, and that ``ppo.train`` builds its envs with the wrapper given.
"""
from __future__ import annotations

import dataclasses
import operator
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.interop.deferred_imports import defer_brax_extras
from jaxrobo.physics.mjx_import import import_mjx

# Brax imports mujoco.mjx: imported here first, MJX's mesh libraries are deferred and its lines about the optional
# Warp backend not said (jaxrobo.physics.mjx_import), as for every other command. JAXopt and Orbax, which Brax
# imports and a jaxrobo run never calls, load on first use (jaxrobo.interop.deferred_imports).
import_mjx()
defer_brax_extras()
from brax.envs import base as brax_base  # noqa: E402
from flax import struct  # noqa: E402

from jaxrobo.task import registry
from jaxrobo.core import rng, spaces
from jaxrobo.task.autoreset import autoreset
from jaxrobo.interop.brax_compat import install_jax_compat
from jaxrobo.core.config import ConfigError
from jaxrobo.task.env import Env, EnvState

__all__ = ["BraxEnv", "State", "make", "wrap_for_training", "TrainingWrapper", "install_jax_compat"]

#: The per-step metrics every BraxEnv reports (tasks add theirs through ``step_metrics``).
BASE_METRICS = ("terminated", "truncated", "physics_nan")


install_jax_compat()  # Brax's trainers, driving these envs, call the JAX functions it restores


@struct.dataclass
class State(brax_base.State):
    """Brax's ``State`` that MuJoCo Playground's wrappers can also drive: they name the simulation state ``data``
    (``state.data``, ``state.replace(data=...)``), Brax ``pipeline_state``; here both name the jaxrobo
    :class:`jaxrobo.task.env.EnvState`. Still a ``brax.envs.base.State`` for Brax's trainers and wrappers."""

    @property
    def data(self) -> Any:
        return self.pipeline_state


def _replace(self: State, **updates: Any) -> State:
    if "data" in updates:
        updates["pipeline_state"] = updates.pop("data")
    return dataclasses.replace(self, **updates)


State.replace = _replace  # after the decorator, which installs its own replace


def _key(rng_key: jax.Array) -> jax.Array:
    """A typed JAX key from Brax's raw ``uint32[2]`` key (a typed key passes through)."""
    if jax.dtypes.issubdtype(rng_key.dtype, jax.dtypes.prng_key):
        return rng_key
    return jax.random.wrap_key_data(rng_key)


def continuous_ids(discrete_id: str | None = None) -> list[str]:
    """The registered ids with continuous actions that declare themselves the counterpart of ``discrete_id``
    (their task class's ``continuous_of``); all such ids when ``discrete_id`` is None."""
    out = []
    for id in registry.registered():
        cls = registry.registration(id).env_class()
        of = getattr(cls, "continuous_of", ())
        if of and (discrete_id is None or discrete_id in of):
            out.append(id)
    return out


class BraxEnv(brax_base.Env):
    """A jaxrobo env with a ``Box`` action space as a Brax ``Env`` (see the module docstring)."""

    def __init__(self, env: Env, params: Any = None, discrete: str = "refuse"):
        """``discrete``: what a ``Discrete(n)`` action space becomes. ``"refuse"`` (default): a ConfigError naming
        the continuous id to use. ``"argmax"``: Brax acts with ``n`` real outputs and the env takes the largest
        one's index, so Brax's PPO and SAC train any id, unchanged (a relaxation for experiments: the ids with
        continuous actions are the ones tuned for them)."""
        if not isinstance(env, Env):
            raise TypeError(f"BraxEnv(env): expected a jaxrobo Env (jaxrobo.make(id)), got {type(env).__name__}")
        if discrete not in ("refuse", "argmax"):
            raise ConfigError(f"BraxEnv discrete={discrete!r}: allowed values are 'refuse', 'argmax'")
        self.env = env
        self.params = env.default_params if params is None else params
        act = env.action_space(self.params)
        self.discrete = discrete
        self._n_discrete = None
        if isinstance(act, spaces.Discrete) and discrete == "argmax":
            self._n_discrete = int(act.n)
            self._unit, self._low, self._high = True, -np.ones(act.n, np.float32), np.ones(act.n, np.float32)
            self._metric_names = BASE_METRICS + tuple(self._task_metrics(None).keys())
            return
        if isinstance(act, spaces.Discrete):
            spec_id = env.spec.id if env.spec is not None else None
            others = continuous_ids(spec_id) if spec_id is not None else []
            hint = (f"use its continuous counterpart {' or '.join(repr(i) for i in others)}" if others else
                    f"use an id with continuous actions ({', '.join(continuous_ids()) or 'none registered'})")
            raise ConfigError(f"BraxEnv: {env.name} has a Discrete({act.n}) action space; Brax's PPO and SAC act "
                              f"with real vectors in [-1, 1]: {hint}, or pass discrete='argmax' (the env takes the "
                              "index of the largest of n outputs)")
        if not isinstance(act, spaces.Box) or len(act.shape) != 1:
            raise ConfigError(f"BraxEnv: {env.name}: action_space() must be a 1-D jaxrobo.core.spaces.Box, got {act!r}")
        low, high = np.asarray(act.low, np.float32), np.asarray(act.high, np.float32)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(high > low)):
            raise ConfigError(f"BraxEnv: {env.name}: the action Box needs finite bounds with high > low (Brax's "
                              f"actions in [-1, 1] are mapped onto them), got low={low}, high={high}")
        self._unit = bool(np.all(low == -1.0) and np.all(high == 1.0))
        self._low, self._high = low, high
        self._metric_names = BASE_METRICS + tuple(self._task_metrics(None).keys())

    # ---- Brax's Env -------------------------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> brax_base.State:
        es = self.env.reset(_key(rng), self.params)
        zero = jnp.zeros((), jnp.float32)
        metrics = {name: zero for name in self._metric_names}
        info = {"truncation": zero, "time_out": zero}
        return State(es, es.obs, zero, zero, metrics, info)

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        es = self.env.step(state.pipeline_state, self.scale_action(action), self.params)
        return self._state(es, state.info, state.metrics)

    @property
    def observation_size(self) -> int:
        return int(self.env.observation_space(self.params).shape[0])

    @property
    def action_size(self) -> int:
        return int(self._low.shape[0])

    @property
    def backend(self) -> str:
        return str(getattr(self.env.options, "backend", "jaxrobo"))

    # ---- helpers ----------------------------------------------------------------------------------------
    def scale_action(self, action: jax.Array) -> jax.Array:
        """Brax's action in [-1, 1] per dimension as the task's action (affine onto the Box bounds; with
        ``discrete="argmax"``, the index of the largest output)."""
        a = jnp.asarray(action, jnp.float32)
        if self._n_discrete is not None:
            return jnp.argmax(a, axis=-1).astype(jnp.int32)
        if self._unit:
            return a
        return jnp.asarray(self._low) + (a + 1.0) * 0.5 * jnp.asarray(self._high - self._low)

    def metrics(self, es: EnvState) -> dict[str, jax.Array]:
        """The per-step metrics of a jaxrobo state (float32 scalars)."""
        out = {"terminated": es.terminated.astype(jnp.float32), "truncated": es.truncated.astype(jnp.float32),
               "physics_nan": es.physics_nan.astype(jnp.float32)}
        out.update(self._task_metrics(es))
        return out

    def _task_metrics(self, es: EnvState | None) -> dict[str, jax.Array]:
        hook = getattr(self.env, "step_metrics", None)
        if hook is None:
            return {}
        if es is None:  # only the names: evaluate the hook's shapes on a reset state
            es = jax.eval_shape(lambda: self.env.reset(jax.random.key(0), self.params))
            return jax.eval_shape(lambda s: hook(s, self.params), es)
        return {k: jnp.asarray(v, jnp.float32) for k, v in hook(es, self.params).items()}

    def _state(self, es: EnvState, info: dict, metrics: dict) -> brax_base.State:
        truncation = es.truncated.astype(jnp.float32)
        info = {**info, "truncation": truncation, "time_out": truncation}
        # The incoming metrics carried forward, jaxrobo's own updated: keys a wrapper added (Brax's EvalWrapper
        # adds 'reward') stay, or a trainer's scan over steps would change its carry's structure.
        return State(es, es.obs, es.reward, es.done.astype(jnp.float32), {**metrics, **self.metrics(es)}, info)

    def __repr__(self) -> str:
        return f"<BraxEnv {self.env.name} backend={self.backend}>"


def make(env_id: str, discrete: str = "refuse", **overrides: Any) -> BraxEnv:
    """``BraxEnv(jaxrobo.make(env_id, **overrides), discrete=discrete)``: any registered id (or ``"module:Id"``);
    a Discrete one is refused with the continuous id to use, unless ``discrete="argmax"``."""
    return BraxEnv(registry.make(env_id, **overrides), discrete=discrete)


def _positive_int(name: str, value: Any) -> int:
    try:
        n = operator.index(value)
    except TypeError:
        raise ConfigError(f"wrap_for_training: {name}={value!r}: expected an integer >= 1") from None
    if n < 1:
        raise ConfigError(f"wrap_for_training: {name}={n}: expected an integer >= 1")
    return n


class TrainingWrapper(brax_base.Wrapper):
    """Batched, auto-resetting (with fresh randomness) training env over a :class:`BraxEnv`; built by
    :func:`wrap_for_training` (see the module docstring)."""

    def __init__(self, env: BraxEnv, episode_length: int, action_repeat: int):
        super().__init__(env)
        self.episode_length, self.action_repeat = episode_length, action_repeat
        # The trainer's episode length is the step limit (checked like any max_episode_steps override).
        self.single = BraxEnv(env.env, env.params.replace(max_episode_steps=episode_length),
                              discrete=env.discrete)

    def reset(self, rng: jax.Array) -> brax_base.State:
        state = jax.vmap(self.single.reset)(rng)
        zeros = jnp.zeros(state.reward.shape, jnp.float32)
        names = ("sum_reward", "length") + tuple(state.metrics)
        state.info["steps"] = zeros
        state.info["episode_done"] = zeros
        state.info["episode_metrics"] = {name: zeros for name in names}
        return state

    def _repeat(self, es: EnvState, action: jax.Array) -> tuple[EnvState, jax.Array, jax.Array, dict]:
        """``action_repeat`` steps of one env, frozen from its first done step: (state, reward sum, steps
        taken, metric sums)."""
        single = self.single
        a = single.scale_action(action)
        zero = jnp.zeros((), jnp.float32)

        def body(carry, _):
            s, total, taken, sums = carry
            nxt = single.env.step(s, a, single.params)
            live = ~s.done
            s = jax.tree.map(lambda new, old: jnp.where(live, new, old), nxt, s)
            m = single.metrics(nxt)
            sums = {k: sums[k] + jnp.where(live, m[k], 0.0) for k in sums}
            return (s, total + jnp.where(live, nxt.reward, 0.0), taken + live.astype(jnp.float32), sums), None

        sums0 = {k: zero for k in single._metric_names}
        # The carry starts live: the wrapper resets every done env before returning it.
        start = es.replace(terminated=jnp.zeros((), bool), truncated=jnp.zeros((), bool))
        (s, total, taken, sums), _ = jax.lax.scan(body, (start, zero, zero, sums0), None, self.action_repeat)
        return s, total, taken, sums

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        single = self.single
        stepped, reward, taken, sums = jax.vmap(self._repeat)(state.pipeline_state, action)
        done = stepped.done
        # Fresh randomness per env: its carried key splits into the next carried key and a reset key.
        keys = jax.vmap(lambda k: rng.split(k, 2))(stepped.key)
        stepped = stepped.replace(key=keys[:, 0])
        nxt = autoreset(single.env, done, keys[:, 1], single.params, stepped)
        donef = done.astype(jnp.float32)
        truncation = stepped.truncated.astype(jnp.float32)
        prev_done = state.info["episode_done"]
        episode = dict(state.info["episode_metrics"])
        episode["sum_reward"] = episode["sum_reward"] * (1 - prev_done) + reward
        episode["length"] = episode["length"] * (1 - prev_done) + taken
        for k, v in sums.items():
            episode[k] = episode[k] * (1 - prev_done) + v
        info = {**state.info, "truncation": truncation, "time_out": truncation,
                "steps": stepped.steps.astype(jnp.float32),
                "episode_done": donef, "episode_metrics": episode}
        return State(nxt, nxt.obs, reward, donef, {**state.metrics, **sums}, info)  # a wrapper's keys kept


def wrap_for_training(env: BraxEnv, episode_length: int = 1000, action_repeat: int = 1,
                      randomization_fn: Callable | None = None) -> TrainingWrapper:
    """The training env Brax's ``ppo.train`` / ``sac.train`` build with ``wrap_env_fn=wrap_for_training``
    (same signature as ``brax.envs.training.wrap``; see the module docstring)."""
    if not isinstance(env, BraxEnv):
        raise TypeError("wrap_for_training(env): expected a jaxrobo.interop.brax_env.BraxEnv, "
                        f"got {type(env).__name__}")
    if randomization_fn is not None:
        raise ConfigError("wrap_for_training: randomization_fn is not supported: Brax's domain randomisation edits "
                          "a Brax System, which a jaxrobo env does not have; vary the env's Params instead "
                          "(BraxEnv(env, params))")
    return TrainingWrapper(env, _positive_int("episode_length", episode_length),
                           _positive_int("action_repeat", action_repeat))
