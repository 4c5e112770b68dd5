"""What every tabular learner shares: parameters, the table state, action choice and the table update.

A learner (see :class:`Learner`) is two pure functions: ``select`` picks an action from one row of action
values and ``target`` gives the value the updated entry moves towards, from the next state's rows. This module
turns them into ``act`` / ``learn`` over a dense ``q[n_tables, n_states, n_actions]`` table, for one table per
environment or one table shared by a whole batch of environments. ``update`` is the same update from rows the
caller already holds: the trainer carries each environment's current rows from one step to the next, so the
table is read once a step (the next state's rows) instead of three times.

``seed_compat=True`` reproduces the seed's learners exactly: the first update of an entry sets it
to the reward itself, a terminal transition still bootstraps, and Q-learning explores by adding noise to the
action values. The default is the textbook form: entries start at 0 and move by ``alpha`` towards the target,
terminal transitions do not bootstrap, exploration is uniform epsilon-greedy.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core import rng
from jaxrobo.core.struct import param, pytree_dataclass


@pytree_dataclass
class AgentParams:
    """Learner hyper-parameters (traced: a sweep vmaps over them). The defaults are the seed's cart-pole values
    and the only home of each: the agent presets (``agents/configs/*.yaml``) list only what differs."""

    alpha: float = param(0.5, low=0.0, low_open=True, high=1.0, doc="learning rate")
    gamma: float = param(0.9, low=0.0, high=1.0, doc="discount factor")
    epsilon: float = param(0.1, low=0.0, high=1.0, doc="initial exploration rate")
    epsilon_discount: float = param(0.999, low=0.0, low_open=True, high=1.0, doc="epsilon *= this per episode")
    epsilon_min: float = param(0.05, low=0.0, high=1.0, doc="epsilon decays only while above this")


@pytree_dataclass
class AgentState:
    """``q``: ``[n_tables, n_states, n_actions]`` action values; ``visited``: the seed's first-update flags."""

    q: jax.Array
    visited: jax.Array | None


SelectFn = Callable[[jax.Array, jax.Array, jax.Array, bool], jax.Array]
TargetFn = Callable[..., tuple[jax.Array, jax.Array]]


@dataclasses.dataclass(frozen=True)
class Learner:
    """A tabular learner: its name, how many tables, on- or off-policy, and its two pure functions.

    ``select(key, q_row, epsilon, seed_compat) -> action``;
    ``target(key, q_next, a2, reward, discount, epsilon) -> (table_index, target_value)``, where ``q_next``
    (``[n_tables, n_actions]``) holds every table's action values in the next state ``s'``.
    """

    name: str
    select: SelectFn
    target: TargetFn
    n_tables: int = 1
    on_policy: bool = False


# ---- reductions over the action axis -----------------------------------------------------------------------
#: Action rows up to this long are reduced with written-out elementwise comparisons: under ``vmap`` on a CPU,
#: XLA's reduction of a few elements per env (a library call per batch) cost more than the rest of the Q update.
UNROLL_ACTIONS = 16


def _fold_actions(row: jax.Array, pairwise: Callable, reduction: Callable) -> jax.Array:
    """``reduction`` over the last (action) axis, written out with ``pairwise`` for short rows."""
    if row.shape[-1] > UNROLL_ACTIONS:
        return reduction(row, axis=-1)
    return functools.reduce(pairwise, (row[..., i] for i in range(row.shape[-1])))


def row_max(row: jax.Array) -> jax.Array:
    """``max`` over the last (action) axis."""
    return _fold_actions(row, jnp.maximum, jnp.max)


def row_min(row: jax.Array) -> jax.Array:
    """``min`` over the last (action) axis."""
    return _fold_actions(row, jnp.minimum, jnp.min)


def row_pick(row: jax.Array, index: jax.Array) -> jax.Array:
    """``row[..., index]`` for a (batched) index into the last (action) axis: written out for short rows, where
    XLA's gather is a separate, slower loop on a CPU."""
    n = row.shape[-1]
    if n > UNROLL_ACTIONS:
        return jnp.take_along_axis(row, jnp.expand_dims(index, -1), axis=-1)[..., 0]
    out = row[..., 0]
    for i in range(1, n):
        out = jnp.where(index == i, row[..., i], out)
    return out


def row_argmax(row: jax.Array) -> jax.Array:
    """``argmax`` over the last (action) axis (the first of equal maxima), as int32."""
    n = row.shape[-1]
    if n > UNROLL_ACTIONS:
        return jnp.argmax(row, axis=-1).astype(jnp.int32)
    best, index = row[..., 0], jnp.zeros(row.shape[:-1], jnp.int32)
    for i in range(1, n):
        better = row[..., i] > best
        best, index = jnp.where(better, row[..., i], best), jnp.where(better, jnp.int32(i), index)
    return index


# ---- action choice -----------------------------------------------------------------------------------------
def argmax_random_ties(q_row: jax.Array, noise: jax.Array) -> jax.Array:
    """argmax of ``q_row``; among equal maxima, the one with the largest ``noise`` (uniform draws) wins."""
    is_max = q_row == row_max(q_row)[..., None]
    return row_argmax(jnp.where(is_max, noise, -1.0))


def pick_among_maxima(q_row: jax.Array, u: jax.Array) -> jax.Array:
    """The greedy action, ties broken uniformly at random by one uniform draw ``u`` in ``[0, 1)``.

    With ``k`` equal maxima the ``floor(u * k)``-th of them is taken: one random number per choice whatever
    the number of actions (written out for small action counts, like :func:`row_max`)."""
    n = q_row.shape[-1]
    is_max = q_row == row_max(q_row)[..., None]
    count = _fold_actions(is_max.astype(jnp.int32), jnp.add, jnp.sum)
    wanted = jnp.minimum(jnp.floor(u * count).astype(jnp.int32), count - 1)
    if n > UNROLL_ACTIONS:
        rank = jnp.cumsum(is_max, axis=-1, dtype=jnp.int32) - 1
        return jnp.argmax(is_max & (rank == wanted[..., None]), axis=-1).astype(jnp.int32)
    choice, seen = jnp.zeros_like(count), jnp.zeros_like(count)
    for i in range(n):
        choice = jnp.where(is_max[..., i] & (seen == wanted), jnp.int32(i), choice)
        seen = seen + is_max[..., i].astype(jnp.int32)
    return choice


def greedy(key: jax.Array, q_row: jax.Array) -> jax.Array:
    """argmax with ties broken uniformly at random (as the seed does)."""
    return pick_among_maxima(q_row, rng.uniform_pair(key)[0])


def epsilon_greedy(key: jax.Array, q_row: jax.Array, epsilon: jax.Array, seed_compat: bool = False) -> jax.Array:
    """Uniform random action with probability ``epsilon``, else greedy (random ties).

    One hash gives two uniforms: the first tosses the coin, the second picks the random action or, when the
    coin says exploit, the greedy action among ties (the branches exclude each other, so one number serves
    both). Random numbers are the largest cost of a tabular step after the physics.
    """
    n = q_row.shape[-1]
    coin, u = rng.uniform_pair(key)
    random_action = jnp.minimum(jnp.floor(u * n), n - 1).astype(jnp.int32)
    return jnp.where(coin < epsilon, random_action, pick_among_maxima(q_row, u))


def greedy_probabilities(q_row: jax.Array) -> jax.Array:
    """The greedy policy's action probabilities, ties sharing the mass equally."""
    is_max = (q_row == row_max(q_row)[..., None]).astype(q_row.dtype)
    return is_max / jnp.sum(is_max)


def epsilon_greedy_probabilities(q_row: jax.Array, epsilon: jax.Array) -> jax.Array:
    n = q_row.shape[-1]
    return (1.0 - epsilon) * greedy_probabilities(q_row) + epsilon / n


# ---- table state -------------------------------------------------------------------------------------------
def init(learner: Learner, n_states: int, n_actions: int, seed_compat: bool = False) -> AgentState:
    """Zero tables (the seed's ``q.get(..., 0.0)``), plus first-update flags in seed-compat mode."""
    q = jnp.zeros((learner.n_tables, n_states, n_actions), jnp.float32)
    visited = jnp.zeros((n_states, n_actions), bool) if seed_compat else None
    return AgentState(q, visited)


def rows(agent: AgentState, s: jax.Array) -> jax.Array:
    """Every table's action values in state ``s``: ``[n_tables, n_actions]``."""
    return agent.q[:, s, :]


def policy_values(q_rows: jax.Array) -> jax.Array:
    """The row of action values the policy uses: the table's own, or the sum of both for Double Q-learning."""
    return q_rows[0] if q_rows.shape[0] == 1 else jnp.sum(q_rows, axis=0)


def action_values(agent: AgentState, s: jax.Array) -> jax.Array:
    """The policy's action values in state ``s`` (see :func:`policy_values`)."""
    return policy_values(rows(agent, s))


def act(learner: Learner, key: jax.Array, agent: AgentState, s: jax.Array, epsilon: jax.Array,
        seed_compat: bool = False) -> jax.Array:
    return learner.select(key, action_values(agent, s), epsilon, seed_compat)


def update(learner: Learner, key: jax.Array, q_s: jax.Array, q_s2: jax.Array, a, r, a2, terminated, epsilon,
           params: AgentParams, seed_compat: bool = False, visited_sa: jax.Array | None = None
           ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(table_index, old_value, new_value)`` of the entry ``(s, a)``, from the rows ``q_s`` and ``q_s2``
    (``[n_tables, n_actions]``: :func:`rows` in ``s`` and ``s'``); ``visited_sa`` is the seed's first-update flag
    of the entry (seed-compat mode only)."""
    discount = params.gamma if seed_compat else params.gamma * (1.0 - terminated.astype(jnp.float32))
    table, target = learner.target(key, q_s2, a2, r, discount, epsilon)
    old = row_pick(q_s[0], a) if q_s.shape[0] == 1 else q_s[table, a]
    new = old + params.alpha * (target - old)
    if seed_compat:
        new = jnp.where(visited_sa, new, r)
    return table, old, new


def new_entry(learner: Learner, key: jax.Array, agent: AgentState, s, a, r, s2, a2, terminated, epsilon,
              params: AgentParams, seed_compat: bool = False) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(table_index, old_value, new_value)`` of the entry ``(s, a)`` after learning from one transition."""
    visited_sa = agent.visited[s, a] if seed_compat else None
    return update(learner, key, rows(agent, s), rows(agent, s2), a, r, a2, terminated, epsilon, params,
                  seed_compat, visited_sa)


def write(agent: AgentState, table, s, a, value, active: jax.Array = True) -> AgentState:
    """The table with entry ``(table, s, a)`` set to ``value``, and its first-update flag set where ``active``."""
    q = agent.q.at[table, s, a].set(value)
    visited = None if agent.visited is None else agent.visited.at[s, a].set(agent.visited[s, a] | active)
    return AgentState(q, visited)


def learn(learner: Learner, key: jax.Array, agent: AgentState, s, a, r, s2, a2, terminated, epsilon,
          params: AgentParams, seed_compat: bool = False, active: jax.Array = True) -> AgentState:
    """Update one environment's own table from one transition; ``active=False`` leaves it unchanged."""
    table, old, new = new_entry(learner, key, agent, s, a, r, s2, a2, terminated, epsilon, params, seed_compat)
    return write(agent, table, s, a, jnp.where(active, new, old), active)


def sum_in_order(index: jax.Array, values: Any, size: int) -> Any:
    """``zeros(size).at[index].add(v)`` for each array ``v`` of the pytree ``values``, with the additions in one
    fixed order on every device.

    A scatter-add of floats runs on a GPU as atomic additions in whatever order the threads arrive, so the
    rounding, and then a tabular run, changes from run to run. Here the values are sorted by index (stably), each
    run of one index is summed by a segmented scan, and each index's total is written once. Every leaf of
    ``values`` shares the one sort, scan and write. The sort's keys are 16-bit where ``size`` allows: a GPU
    radix-sorts them in half the passes, and a stable sort's order does not depend on the key's width."""
    key_dtype = jnp.uint16 if size <= 1 << 16 else jnp.int32
    keys, order = jax.lax.sort((index.astype(key_dtype), jnp.arange(index.shape[0], dtype=jnp.int32)),
                               num_keys=1, is_stable=True)
    leaves, treedef = jax.tree.flatten(values)
    leaves = [v[order] for v in leaves]
    change = keys[1:] != keys[:-1]
    first = jnp.concatenate([jnp.ones((1,), bool), change])
    last = jnp.concatenate([change, jnp.ones((1,), bool)])

    def combine(x, y):
        (vx, fx), (vy, fy) = x, y
        return [jnp.where(fy, b, a + b) for a, b in zip(vx, vy)], fx | fy

    sums, _ = jax.lax.associative_scan(combine, (leaves, first))
    where = jnp.where(last, keys.astype(jnp.int32), size)
    return jax.tree.unflatten(treedef, [jnp.zeros((size,), v.dtype).at[where].set(t, mode="drop")
                                        for v, t in zip(leaves, sums)])


def learn_shared(learner: Learner, keys: jax.Array, agent: AgentState, s, a, r, s2, a2, terminated, epsilon,
                 params: AgentParams, seed_compat: bool = False, active: jax.Array | None = None,
                 ordered: bool = False) -> AgentState:
    """Update one table shared by a batch of environments from one transition each.

    Every environment computes its new entry value from the same table; where several hit the same entry,
    the entry takes the mean of their new values (a synchronous, batched TD update). ``ordered``: sum the new
    values with :func:`sum_in_order` instead of a scatter-add (reproducible on a GPU; rounds in another order
    than the scatter-add where an entry has several).
    """
    active = jnp.ones(s.shape, bool) if active is None else active
    table, _, new = jax.vmap(new_entry, in_axes=(None, 0, None, 0, 0, 0, 0, 0, 0, 0, None, None))(
        learner, keys, agent, s, a, r, s2, a2, terminated, epsilon, params, seed_compat)
    w = active.astype(jnp.float32)
    if ordered:  # the counts ride along the values' sort (one scatter fewer, no atomics)
        _, n_states, n_actions = agent.q.shape
        flat = (table * n_states + s) * n_actions + a
        total, count = (x.reshape(agent.q.shape) for x in sum_in_order(flat, (w * new, w), agent.q.size))
    else:
        total = jnp.zeros_like(agent.q).at[table, s, a].add(w * new)
        count = jnp.zeros_like(agent.q).at[table, s, a].add(w)
    # Counts are whole numbers, exact in float32 in any order of addition: both branches count alike.
    q = jnp.where(count > 0, total / jnp.maximum(count, 1.0), agent.q)
    visited = None
    if agent.visited is not None:
        visited = agent.visited.at[s, a].max(active)
    return AgentState(q, visited)


# ---- exploration schedule ----------------------------------------------------------------------------------
def decay_epsilon(epsilon: jax.Array, params: AgentParams) -> jax.Array:
    """The seed's per-episode rule: ``epsilon *= epsilon_discount`` while ``epsilon > epsilon_min``."""
    return jnp.where(epsilon > params.epsilon_min, epsilon * params.epsilon_discount, epsilon)


def epsilon_schedule(params: AgentParams, nepisodes: int) -> np.ndarray:
    """Epsilon used in each episode ``0 .. nepisodes-1`` (decayed once before the first, as in the seed)."""
    eps = np.empty(nepisodes, np.float64)
    e = float(params.epsilon)
    for i in range(nepisodes):
        if e > float(params.epsilon_min):
            e *= float(params.epsilon_discount)
        eps[i] = e
    return eps.astype(np.float32)
