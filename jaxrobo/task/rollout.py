"""Episodes of a policy, in one compiled computation: greedy evaluation of tables, random baselines, success rates.

Every place that runs a policy's episodes goes through here: the trainer's evaluation
(:meth:`jaxrobo.training.trainer.Trainer.evaluate`), the quadcopter flights (:mod:`jaxrobo.show`, the benchmarks) and
the greedy policy of a video (:func:`jaxrobo.pictures.render.q_policy`). So a greedy policy breaks ties one way
everywhere: uniformly at random among the maximal action values, drawn from the step's key (:func:`greedy_action`, which
is :func:`jaxrobo.tabular.learner.greedy`); only a policy that leaves JAX (``jaxrobo export``) takes the first maximal
action instead, and ``greedy_policy(..., ties="first")`` is its JAX twin.

Public surface:

``Policy``
    ``policy(key, obs) -> action``: a pure, traceable function of the step's key and one observation.
:func:`greedy_action` ``(key, values)``
    The greedy action of a row of action values, ties broken at random by ``key``: the one tie-breaking rule.
:func:`greedy_policy` ``(q, discretiser, ties="random")``
    Greedy in one learner's tables ``q [n_tables, n_states, n_actions]`` (Double Q-learning acts on the sum);
    ``ties="first"``: the first maximal action instead, deterministic (what an exported policy does).
:func:`random_policy` ``(n_actions)``
    Uniform random actions.
:func:`rollout` ``(env, policy, key, n_episodes, horizon=None, params=None, observe=None)``
    ``n_episodes`` episodes of at most ``horizon`` steps, vmapped: returns, lengths, the first and last states,
    and with ``observe`` a per-step record (for flight plots).
:func:`outcomes` ``(out)``
    How each episode of a ``rollout`` ended: returns, lengths, ``terminated`` and, where the task has one, ``arrived``.
:func:`success_rate` ``(env, policy, key, n_episodes=200, params=None, horizon=None)``
    For tasks whose task variables carry ``arrived`` / ``crashed`` flags (QuadcopterGoto): the fractions of
    episodes that arrive, fail or time out, and the mean episode length, as Python floats.
:func:`host_policy` ``(policy, seed=0)``
    A ``Policy`` as a host function ``obs -> int`` with its own key chain, for host loops such as
    :func:`jaxrobo.pictures.render.rollout_frames`.

:func:`rollout_start`, :func:`rollout_advance`, :func:`rollout_end`
    The same episodes as :func:`rollout` (without ``observe``) in segments of steps, for progress between them.

Keys: episode ``i`` uses ``k = split(key, n_episodes)[i]``, resets from ``split(k)[0]`` and takes its ``t``-th
action with ``split(split(k)[1], horizon)[t]``; the trainer's evaluation figures depend on this layout.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.tabular import learner as tabular

__all__ = ["Policy", "greedy_action", "greedy_policy", "random_policy", "rollout", "rollout_start", "rollout_advance",
           "rollout_end", "outcomes", "success_rate", "host_policy"]

#: How a greedy policy breaks ties between equal action values (:func:`greedy_policy`).
TIES = ("random", "first")

#: ``(key, obs) -> action``.
Policy = Callable[[jax.Array, jax.Array], jax.Array]


def greedy_action(key: jax.Array, values: jax.Array) -> jax.Array:
    """argmax of ``values`` (the last axis), ties broken uniformly at random with ``key``."""
    return tabular.greedy(key, values)


def greedy_policy(q: jax.Array, discretiser: Callable[[jax.Array], jax.Array], ties: str = "random") -> Policy:
    """Greedy in one learner's tables ``q [n_tables, n_states, n_actions]``: the action values of the state
    ``discretiser(obs)`` are the table's row, or the sum of both rows for Double Q-learning
    (:func:`jaxrobo.tabular.learner.policy_values`, as the learner acts). ``ties``: ``"random"`` breaks them at
    random with the step's key (:func:`greedy_action`, every evaluation); ``"first"`` takes the first maximal
    action, a deterministic policy (the one ``jaxrobo export`` writes and its numpy runner acts by).
    ``discretiser`` must be traceable (a :class:`jaxrobo.tabular.discretise.Discretiser`)."""
    q = jnp.asarray(q)
    if q.ndim != 3:
        raise ValueError(f"q has shape {q.shape}; expected [n_tables, n_states, n_actions]")
    if ties not in TIES:
        raise ValueError(f"ties={ties!r}: allowed values are {', '.join(TIES)}")
    if ties == "first":  # the 0-th of the maxima: pick_among_maxima with the uniform draw 0
        return lambda k, obs: tabular.pick_among_maxima(tabular.policy_values(q[:, discretiser(obs), :]),
                                                        jnp.float32(0))
    return lambda k, obs: greedy_action(k, tabular.policy_values(q[:, discretiser(obs), :]))


def random_policy(n_actions: int) -> Policy:
    """Uniformly random actions in ``0 .. n_actions-1``."""
    return lambda k, obs: jax.random.randint(k, (), 0, n_actions, dtype=jnp.int32)


def _horizon(env: Any, horizon: int | None) -> int:
    if horizon is not None:
        if int(horizon) < 1:
            raise ValueError(f"horizon={horizon}: expected an integer >= 1")
        return int(horizon)
    spec = getattr(env, "spec", None)
    if spec is None or not spec.max_episode_steps:
        raise ValueError(f"{env!r} has no spec.max_episode_steps: pass horizon (the step cap per episode)")
    return int(spec.max_episode_steps)


def rollout(env: Any, policy: Policy, key: jax.Array, n_episodes: int, horizon: int | None = None,
            params: Any = None, observe: Callable[[Any], Any] | None = None) -> dict[str, Any]:
    """``n_episodes`` episodes of ``policy``, each of at most ``horizon`` steps (default: the env spec's
    ``max_episode_steps``); traceable (jit it, or call it inside a jitted function).

    Returns a dict of ``[n_episodes, ...]`` arrays: ``return`` (sum of rewards until the episode ends),
    ``length`` (steps until it ends, ``horizon`` if it does not), ``first`` (the reset ``EnvState``) and
    ``last`` (the state the episode ended in; its ``task`` holds a task's outcome flags). With ``observe``
    (``EnvState -> pytree``, e.g. the robot's position) also ``trace`` (``observe`` of the first state and of
    the state after each step, frozen once the episode has ended: ``[n, horizon+1, ...]``), ``alive``
    (``[n, horizon+1]``, True while the episode runs, including its last state), ``reward`` (``[n, horizon]``,
    0 after the end) and ``action`` (``[n, horizon]``, meaningful where ``alive[:, 1:]``).

    The env keeps stepping after an episode ends (a scan has a fixed length); nothing after the end is counted.
    """
    params = env.default_params if params is None else params
    horizon = _horizon(env, horizon)

    def episode(k):
        k_reset, k_run = jax.random.split(k)
        state = env.reset(k_reset, params)

        def body(carry, k_step):
            state, last, ret, length, alive = carry
            nxt, last, ret, length, a = _step(env, policy, params, state, last, ret, length, alive, k_step)
            out = None if observe is None else (observe(last), alive, jnp.where(alive, nxt.reward, 0.0), a)
            alive = alive & ~nxt.done
            return (nxt, last, ret, length, alive), out

        init = (state, state, jnp.float32(0), jnp.int32(0), jnp.bool_(True))
        (_, last, ret, length, _), steps = jax.lax.scan(body, init, jax.random.split(k_run, horizon))
        out = {"return": ret, "length": length, "first": state, "last": last}
        if observe is not None:
            seen, alive, reward, action = steps
            out["trace"] = jax.tree.map(lambda x0, xs: jnp.concatenate([x0[None], xs]), observe(state), seen)
            out["alive"] = jnp.concatenate([jnp.ones(1, bool), alive])
            out["reward"], out["action"] = reward, action
        return out

    return jax.vmap(episode)(jax.random.split(key, n_episodes))


def _step(env: Any, policy: Policy, params: Any, state: Any, last: Any, ret: jax.Array, length: jax.Array,
          live: jax.Array, k_step: jax.Array) -> tuple[Any, Any, jax.Array, jax.Array, jax.Array]:
    """One step of one episode, counted where ``live``: the one home of an episode's step, for :func:`rollout`
    and the segments of :func:`rollout_advance` (the same operations, so the same numbers)."""
    a = policy(k_step, state.obs)
    nxt = env.step(state, a, params)
    ret = ret + jnp.where(live, nxt.reward, 0.0)
    length = length + live.astype(jnp.int32)
    last = jax.tree.map(lambda n, o: jnp.where(live, n, o), nxt, last)
    return nxt, last, ret, length, a


# ---- a rollout in segments: the same episodes, run a few hundred steps per call --------------------------------
# A long evaluation is one compiled scan of ``horizon`` steps with nothing to report until it ends; cut into
# segments, the host sees the steps done and the episodes still running between calls (progress with an ETA),
# and stops once every episode has ended (nothing after the end is counted, so the figures are the same).
def rollout_start(env: Any, key: jax.Array, n_episodes: int, params: Any = None) -> dict[str, Any]:
    """The carry of :func:`rollout`'s ``n_episodes`` episodes before their first step (the same keys): ``state``,
    ``last``, ``first``, ``return``, ``length``, ``alive`` and ``key`` (each episode's step keys' root)."""
    params = env.default_params if params is None else params

    def episode(k):
        k_reset, k_run = jax.random.split(k)
        state = env.reset(k_reset, params)
        return {"state": state, "last": state, "first": state, "return": jnp.float32(0), "length": jnp.int32(0),
                "alive": jnp.bool_(True), "key": k_run}

    return jax.vmap(episode)(jax.random.split(key, n_episodes))


def rollout_advance(env: Any, policy: Policy, carry: dict[str, Any], t0: jax.Array, steps: int, horizon: int,
                    params: Any = None) -> dict[str, Any]:
    """``carry`` (:func:`rollout_start`) after steps ``t0 .. t0 + steps - 1`` of its episodes, those below
    ``horizon`` (``t0`` may be traced: one compiled segment serves all; ``steps`` is static)."""
    params = env.default_params if params is None else params

    def episode(c):
        # Step t's key is split(key, horizon)[t] as in rollout; the segment past the horizon steps uncounted.
        keys = jax.random.split(c["key"], horizon)
        keys = jnp.concatenate([keys, keys[:steps]])
        seg = jax.lax.dynamic_slice_in_dim(keys, t0, steps)
        valid = (t0 + jnp.arange(steps)) < horizon

        def body(inner, xs):
            state, last, ret, length, alive = inner
            k_step, ok = xs
            nxt, last, ret, length, _ = _step(env, policy, params, state, last, ret, length, alive & ok, k_step)
            return (nxt, last, ret, length, alive & ~(nxt.done & ok)), None

        init = (c["state"], c["last"], c["return"], c["length"], c["alive"])
        (state, last, ret, length, alive), _ = jax.lax.scan(body, init, (seg, valid))
        return {**c, "state": state, "last": last, "return": ret, "length": length, "alive": alive}

    return jax.vmap(episode)(carry)


def rollout_end(carry: dict[str, Any]) -> dict[str, Any]:
    """What :func:`rollout` returns (without ``observe``) from a carry advanced to the horizon or until no
    episode is ``alive``."""
    return {"return": carry["return"], "length": carry["length"], "first": carry["first"], "last": carry["last"]}


def outcomes(out: dict[str, Any]) -> dict[str, jax.Array]:
    """How each episode of a :func:`rollout` ended: ``return``, ``length``, ``terminated`` and, for a task whose
    task variables carry an ``arrived`` flag (QuadcopterGoto, ArmReach), ``arrived``; each ``[n_episodes]``."""
    last = out["last"]
    res = {"return": out["return"], "length": out["length"], "terminated": last.terminated}
    arrived = getattr(last.task, "arrived", None)
    if arrived is not None:
        res["arrived"] = jnp.asarray(arrived, bool)
    return res


def success_rate(env: Any, policy: Policy, key: jax.Array, n_episodes: int = 200, params: Any = None,
                 horizon: int | None = None) -> dict[str, float]:
    """Fractions of ``n_episodes`` episodes that arrive (``success``), fail (``failure``: crash, leaving the
    workspace, a limit) or run out of steps (``timeout``), and the mean episode length (``mean_steps``), for a
    task whose task variables carry ``arrived`` and ``crashed`` flags (QuadcopterGoto)."""
    probe = jax.eval_shape(lambda k: env.reset(k, env.default_params if params is None else params),
                           jax.random.key(0))
    task = getattr(probe, "task", None)
    if not (hasattr(task, "arrived") and hasattr(task, "crashed")):
        raise ValueError(f"{getattr(env, 'name', env)!r}: success_rate needs a task with arrived/crashed flags")
    last = jax.jit(lambda k: rollout(env, policy, k, n_episodes, horizon, params)["last"])(key)
    arrived, crashed = np.asarray(last.task.arrived), np.asarray(last.task.crashed)
    return {"success": float(arrived.mean()), "failure": float(crashed.mean()),
            "timeout": float((~arrived & ~crashed).mean()), "mean_steps": float(np.asarray(last.steps).mean())}


class host_policy:  # noqa: N801 - used like a function: host_policy(policy, seed)(obs)
    """``policy`` as a host function ``obs -> int``: jitted once, the ``t``-th call acting with
    ``fold_in(key(seed), t)``, so a host loop breaks ties by the same rule as :func:`rollout`."""

    def __init__(self, policy: Policy, seed: int = 0):
        self._act = jax.jit(policy)
        self._key = jax.random.key(seed)
        self._t = 0

    def __call__(self, obs: Any) -> int:
        k = jax.random.fold_in(self._key, self._t)
        self._t += 1
        return int(self._act(k, jnp.asarray(obs)))
