"""An env's reset and step compiled once for host loops: the Gymnasium adapter and rendering both step envs one
call at a time from Python, and share these compiled functions (one compile per env configuration and plan).

Public surface: :func:`compiled_for` (``reset(key, params)``, ``step(state, action, params)`` and their batched
``vreset``/``vstep`` (next-step autoreset), ``vstep_same`` (same-step autoreset), ``vstep_plain`` (none) and
``vreset_where`` (reset some envs of a batch), and ``reset_chain`` (the first states of :data:`CHAIN` successive
episodes, for a single env stepped on the host), each returning the state and one packed float32 row per env: the
observation followed by :data:`N_EXTRA` step results). The class behind it is private.
"""
from __future__ import annotations

import dataclasses
from typing import Any

N_EXTRA = 5  # reward, terminated, truncated, physics_nan, steps follow the observation in the packed row
#: Episodes one ``reset_chain`` call starts: a host-stepped env pays one jitted call per this many resets (a call
#: costs about as many microseconds as a short episode of host steps; a seeded reset starts a new chain).
CHAIN = 128


def _pack(state: Any) -> Any:
    """Observation and step results in one float32 row, so the host reads them with one transfer."""
    import jax.numpy as jnp

    extra = jnp.stack([state.reward, state.terminated, state.truncated, state.physics_nan, state.steps])
    return jnp.concatenate([jnp.ravel(state.obs).astype(jnp.float32), extra.astype(jnp.float32)])


@dataclasses.dataclass
class _Compiled:
    """Jitted single and batched reset/step of one env; params are arguments, so one compile serves all. Each
    function is traced under ``plan`` (a :class:`jaxrobo.speed.plan.ExecutionPlan`) and compiled with its options."""

    env: Any
    plan: Any

    def __post_init__(self) -> None:
        import jax
        import jax.numpy as jnp

        from jaxrobo.speed.plan import step_batch

        env, plan = self.env, self.plan

        def reset(key, params):
            state = env.reset(key, params)
            return state, _pack(state)

        def step(state, action, params):
            state = env.step(state, action, params)
            return state, _pack(state)

        def next_key(key):
            return jax.random.split(key)[1]

        def vreset(keys, params):
            states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
            return states, jnp.zeros(keys.shape, bool), jax.vmap(_pack)(states)

        def vstep(states, needs_reset, actions, params):
            # Next-step autoreset: an env that finished on the previous step starts its next episode now, from the
            # key its state carried, and this step's action for it is ignored.
            stepped = step_batch(env, states, actions, params, plan)  # grouped on a GPU, as the trainer steps

            def with_resets(stepped):
                from jaxrobo.task.autoreset import autoreset

                return autoreset(env, needs_reset, jax.vmap(next_key)(states.key), params, stepped)

            new = jax.lax.cond(jnp.any(needs_reset), with_resets, lambda s: s, stepped)
            return new, new.terminated | new.truncated, jax.vmap(_pack)(new)

        def vstep_same(states, actions, params):
            # Same-step autoreset: an env that finishes on this step starts its next episode at once, from the key
            # its final state carries (the single env's unseeded reset rule). The row holds the final observation
            # and this step's results, then the observation the env is left at (the reset one where done).
            stepped = step_batch(env, states, actions, params, plan)
            done = stepped.terminated | stepped.truncated

            def with_resets(stepped):
                from jaxrobo.task.autoreset import autoreset

                return autoreset(env, done, jax.vmap(next_key)(stepped.key), params, stepped)

            new = jax.lax.cond(jnp.any(done), with_resets, lambda s: s, stepped)
            obs = jnp.reshape(new.obs, (done.shape[0], -1)).astype(jnp.float32)
            return new, jnp.concatenate([jax.vmap(_pack)(stepped), obs], axis=1)

        def vstep_plain(states, actions, params):
            # No autoreset: the caller resets finished envs itself (vreset_where).
            new = step_batch(env, states, actions, params, plan)
            return new, jax.vmap(_pack)(new)

        def vreset_where(states, needs_reset, mask, seeded, seed_keys, params):
            # Reset only the envs in ``mask``: from their seed's key where ``seeded``, else from the key their state
            # carries (the single env's unseeded reset rule); the other envs keep their state.
            from jaxrobo.task.autoreset import autoreset

            chained = jax.random.key_data(jax.vmap(next_key)(states.key))
            data = jnp.where(seeded[:, None], jax.random.key_data(seed_keys), chained)
            keys = jax.random.wrap_key_data(data, impl=jax.random.key_impl(states.key))
            new = autoreset(env, mask, keys, params, states)
            return new, needs_reset & ~mask, jax.vmap(_pack)(new)

        def reset_chain(key, params):
            # The first states of CHAIN successive episodes from ``key``, each episode's key the next of the last
            # one's state key (the unseeded reset rule), with the CHAIN + 1 reset keys as key data (the last starts
            # the chain after these): every episode starts from exactly the state the single env's own reset would
            # draw. The
            # physics state is cut to its coordinates (a JointState), all a host step reads of it.
            from jaxrobo.physics.sim import JointState
            from jaxrobo.task.env import simulator_of

            def body(k, _):  # only the key is kept: the rest of this reset is dead code in the loop
                return next_key(env.reset(k, params).key), k

            last, keys = jax.lax.scan(body, key, None, length=CHAIN)
            states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)  # the resets themselves, side by side
            sim, ps = simulator_of(env), states.pipeline_state
            data = jax.random.key_data(jnp.concatenate([keys, last[None]]))
            joints = JointState(jax.vmap(sim.qpos)(ps), jax.vmap(sim.qvel)(ps))
            return dataclasses.replace(states, key=jax.random.key_data(states.key), pipeline_state=joints), data

        def jit(fn, **kw):
            return jax.jit(plan.traced(fn), compiler_options=plan.xla_options, **kw)

        self.reset = jit(reset)
        self.step = jit(step)
        self.next_key = jit(next_key)
        self.reset_chain = jit(reset_chain)
        self.vnext_key = jit(jax.vmap(next_key))
        self.vreset = jit(vreset)
        self.vstep = jit(vstep, donate_argnums=(0,))
        self.vstep_same = jit(vstep_same, donate_argnums=(0,))
        self.vstep_plain = jit(vstep_plain, donate_argnums=(0,))
        self.vreset_where = jit(vreset_where, donate_argnums=(0,))


_CACHE: dict[Any, _Compiled] = {}


def compiled_for(env: Any, plan: Any = None) -> _Compiled:
    """The shared jitted functions of ``env`` under ``plan`` (default: ``ExecutionPlan.for_run(env)``): keyed by
    class, options (static) and plan, so every adapter of the same env configuration and plan reuses one
    compilation whatever its parameters."""
    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.core.precision import check_precision

    check_precision(getattr(env, "name", type(env).__name__))  # x64 may have been switched on since the env was built
    plan = ExecutionPlan.for_run(env) if plan is None else plan
    try:
        key = (type(env), env.options, plan)
        hash(key)
    except (AttributeError, TypeError):
        return _Compiled(env, plan)  # unhashable options: compile per instance
    if key not in _CACHE:
        _CACHE[key] = _Compiled(env, plan)
    return _CACHE[key]
