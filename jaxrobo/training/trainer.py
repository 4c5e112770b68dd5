"""The trainer: how a run is shaped (:class:`TrainConfig`), its carry (:class:`Runner`) and the jitted step.

Each environment runs the seed's experiment with its own learner and table (or, with ``shared_table``, all of
them feed one table): ``nepisodes`` episodes of at most ``nsteps`` steps, the learner updated every step,
``epsilon *= epsilon_discount`` at the start of every episode while it is above ``epsilon_min``. Environments
that finish an episode reset with fresh randomness at once and carry on with their next episode; an
environment that has done all its episodes stops learning and recording, so the results do not depend on how
long the others take, nor on the chunk length.

That per-env episode budget is the seed's experiment and the default, but it leaves the batch idle: the envs
that learned best (the longest episodes) hold the whole batch until they finish. Two run-wide budgets keep every
slot busy (:attr:`Trainer.budget`): ``total_steps`` (each env steps ``ceil(total_steps / n_envs)`` steps, whatever
its episodes' lengths: a full batch until the last chunk) and ``total_episodes`` (every env steps until the run
has finished that many episodes: for a shared table, the episodes that table learned from). Under either,
``nepisodes`` is how many episodes each env records (later ones are counted, not stored), an episode cut by the
end of the budget is not recorded (records count whole episodes), and the results still do not depend on the
chunk length.

The whole step (act → env step → discretise → learn → record → auto-reset) is one function scanned over
``chunk_steps`` steps (:meth:`Trainer.run_chunk`); ``init`` and ``run_chunk`` take the learner and env
parameters as arguments, so a sweep vmaps them over a configuration axis (:mod:`jaxrobo.training.sweep`). Nothing here
runs a host loop: :mod:`jaxrobo.training.driver` compiles the chunk and runs it chunk after chunk.

With ``snapshots`` (a shared table only) the carry also keeps a few late tables (:meth:`Trainer.keep_snapshots`,
at chunk boundaries near 95 %, 90 %, ... of the budget), and a finished run keeps the best of them and its final
table on greedy flights of its own (:meth:`Trainer.final_table`): see that method for why.

Public surface: :class:`TrainConfig`, :class:`Runner`, :class:`Trainer` (``init``, ``step``, ``run_chunk``,
``keep_snapshots``, ``snapshot_points``, ``final_table``, ``max_chunks``, ``budget``, ``budget_total``, ``progress``,
``evaluate``, ``evaluate_episodes``), :data:`SNAPSHOT_SPACING`, :data:`MAX_SNAPSHOTS`, :func:`make_discretiser_for`
(defined in :mod:`jaxrobo.tabular.discretise`, where the plan's default reads it too), :func:`progress_stats`. Names
with a leading underscore are private.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxrobo.physics import libdevice_sincos
from jaxrobo.tabular import learner as tabular
from jaxrobo.tabular.learner import AgentParams, AgentState, Learner
from jaxrobo.task import autoreset, registry, rollout
from jaxrobo.core import rng
from jaxrobo.tabular.discretise import MODES, Discretiser, make_discretiser_for
from jaxrobo.task.env import Env, EnvState, ranking, reset_shapes, task_fields
from jaxrobo.speed.plan import FUSED_CHOICES, ExecutionPlan, check_pallas, map_groups, physics_kernel, step_batch
from jaxrobo.core.struct import param, pytree_dataclass


#: Spacing of the late tables kept for the final choice (:attr:`TrainConfig.snapshots`), as a share of the
#: budget: snapshot k is the table at the last chunk boundary at or before ``1 - k * SNAPSHOT_SPACING`` of it.
SNAPSHOT_SPACING = 0.05
#: Most snapshots: the earliest then lies at half the budget.
MAX_SNAPSHOTS = 10
#: Learning-target checks are spaced so that a check's worst case (every episode flying the whole horizon) costs
#: at most 1/TARGET_CHECK_SPACING of the training between two checks (:meth:`Trainer.target_every`).
TARGET_CHECK_SPACING = 2


@pytree_dataclass
class TrainConfig:
    """How a run is shaped (static: these fix array shapes and code paths)."""

    agent: str = param("qlearn", choices=tuple(registry.learners()), static=True, doc="tabular learner")
    n_envs: int = param(64, low=1, static=True, doc="independent copies of the experiment run at once")
    nepisodes: int = param(1000, low=1, static=True, doc="episodes per environment")
    nsteps: int = param(1000, low=1, static=True, doc="step cap per episode in the training loop")
    seed: int = param(0, low=0, static=True, host_only=True, doc="random seed; the same seed gives the same results")
    seed_compat: bool = param(False, static=True,
                              doc="reproduce the seed's learners exactly (docs/cartpole.md, Presets)")
    shared_table: bool = param(False, static=True, doc="one table learning from all environments")
    discretiser: str = param("bins", choices=MODES, static=True, doc="how observations become states")
    number_splits: int = param(10, low=1, high=10_000, static=True, doc="bins per observation dimension")
    bins: tuple | None = param(None, kind=tuple, static=True, doc="bins per dimension (overrides number_splits)")
    state_low: tuple | None = param(None, kind=tuple, static=True, doc="discretiser lower bounds (default: task's)")
    state_high: tuple | None = param(None, kind=tuple, static=True, doc="discretiser upper bounds")
    edges: tuple | None = param(None, kind=tuple, static=True, doc="interior bin edges per dimension (mode edges)")
    resolution: float = param(0.1, low=0.0, low_open=True, static=True, doc="bin width of mode round")
    total_steps: int = param(0, low=0, high=2**53, static=True,
                             doc="step budget: env steps of the whole run, all envs together (Brax's num_timesteps, "
                                 "SB3's total_timesteps): every env steps ceil(total_steps / n_envs) steps, its "
                                 "episodes restarting as they end, and nepisodes is then how many episodes each env "
                                 "records; 0: the episode budget (nepisodes per env)")
    total_episodes: int = param(0, low=0, static=True,
                                doc="episode budget of the whole run, all envs together: every env steps until the "
                                    "run has finished this many episodes (with shared_table: the table's episodes), "
                                    "and nepisodes is then how many episodes each env records; 0: nepisodes per env")
    chunk_steps: int = param(1000, low=1, static=True, doc="steps per compiled chunk between progress updates")
    record_episodes: bool = param(True, static=True, doc="keep every episode's return and length")
    eval_episodes: int = param(100, low=0, static=True, doc="greedy evaluation episodes per evaluated table")
    eval_envs: int = param(8, low=1, static=True, doc="how many trained tables to evaluate")
    devices: int = param(0, low=0, static=True,
                         doc="devices the envs are split over, each stepping n_envs / devices of them (0: every "
                             "local device, or the most that divide n_envs; of every host under jax.distributed)")
    env_group: int = param(0, low=0, static=True,
                           doc="envs stepped together, group after group (0: automatic, see ExecutionPlan)")
    fused: str = param("auto", choices=("auto",) + FUSED_CHOICES, static=True,
                       doc="how a closed form's substeps and kernels run (auto: ExecutionPlan.for_run's choice for "
                           "the device and run; off, xla or pallas: that one, pallas refused where it cannot run)")
    snapshots: int = param(0, low=0, high=MAX_SNAPSHOTS, static=True,
                           doc="late tables kept for the final choice (shared_table only): the table at the last "
                               "chunk boundary at or before 95 %, 90 %, ... of the budget; at the end of the run the "
                               "final table and these fly snapshot_episodes greedy episodes and the best, by the "
                               "task's learning target, becomes the run's table; 0: the final table")
    snapshot_episodes: int = param(100, low=1, static=True,
                                   doc="greedy episodes each candidate table flies for the final choice (snapshots)")
    stop_at_target: bool = param(True, static=True,
                                 doc="stop once the task's learning target holds on fresh greedy episodes (eval_envs "
                                     "tables x eval_episodes, checked every target_every chunks and confirmed on as "
                                     "many fresh episodes again); "
                                     "the budget is then a cap; no effect for a task that declares no target")
    target_every: int = param(0, low=0, static=True,
                              doc="chunks between learning-target checks (0: automatic, so that a check costs at "
                                  "most about half the training between two checks, and far less before the policy "
                                  "has learned)")


@pytree_dataclass
class Runner:
    """The training carry: a batch of environments, their learner state and their records."""

    env_state: EnvState
    agent: AgentState
    s: jax.Array
    #: Each env's table rows at ``s`` (``[n_envs, n_tables, n_actions]``), carried so that a step reads the
    #: table once (the next state's rows) instead of three times; ``None`` with a shared table, where other envs'
    #: updates would make a carried copy stale.
    q_rows: jax.Array | None
    action: jax.Array
    epsilon: jax.Array
    episode: jax.Array
    ep_return: jax.Array
    key: jax.Array
    returns: jax.Array
    lengths: jax.Array
    terminated: jax.Array
    nan_episodes: jax.Array
    env_steps: jax.Array
    #: The late tables kept for the final choice (``[snapshots, n_tables, n_states, n_actions]``,
    #: :meth:`Trainer.final_table`); ``None`` without ``snapshots``.
    snapshots: jax.Array | None = None


class Trainer:
    """Pure ``init`` / ``run_chunk`` / ``evaluate`` for one env, learner, discretiser and config."""

    def __init__(self, env: Env, config: TrainConfig, discretiser: Discretiser | None = None,
                 learner: Learner | None = None, *, plan: ExecutionPlan | None = None):
        """``plan``: how the run is executed (:class:`jaxrobo.speed.plan.ExecutionPlan`; default: the plan for this env
        and config on the default device). It changes the compiled program; the values only in their last bits, where
        a GPU rounds the Pallas kernels or a shared table's ordered sums otherwise (see the plan's fields)."""
        self.env = env
        self.config = config
        self.learner = learner or registry.learner(config.agent)
        self.disc = discretiser or make_discretiser_for(env, config)
        self.n_actions = env.num_actions
        # The default plan of this run: its learner and discretiser decide whether the whole chunk runs as one kernel.
        self.plan = ExecutionPlan.for_run(env, config, agent=self.learner.name, discretiser=self.disc) \
            if plan is None else plan
        if config.shared_table and self.learner.n_tables > 1 and config.seed_compat:
            raise ValueError("seed_compat applies to one-table learners; double_q has no seed form")
        if self.plan.fused == "pallas":
            check_pallas(self)

    # ---- the plan's choices the step reads (assigning one replaces the plan) --------------------------------
    @property
    def env_group(self) -> int | None:
        """Envs stepped at once (``plan.env_group``; None: the whole batch)."""
        return self.plan.env_group

    @env_group.setter
    def env_group(self, value: int | None) -> None:
        self.plan = self.plan.replace(env_group=value)

    @property
    def reset_capacity(self) -> int:
        """Most envs reset per step by gathering them (``plan.reset_capacity``; None there: every env)."""
        return self.config.n_envs if self.plan.reset_capacity is None else self.plan.reset_capacity

    @reset_capacity.setter
    def reset_capacity(self, value: int | None) -> None:
        self.plan = self.plan.replace(reset_capacity=value)

    @property
    def carry_rows(self) -> bool:
        """Carry each env's table rows at its state (``plan.carry_rows``; never with a shared table)."""
        return self.plan.carry_rows and not self.config.shared_table

    @carry_rows.setter
    def carry_rows(self, value: bool) -> None:
        self.plan = self.plan.replace(carry_rows=value)

    # ---- the run's budget ------------------------------------------------------------------------------------
    @property
    def budget(self) -> str:
        """Which budget ends the run: ``"episodes"`` (the seed's: ``nepisodes`` per env, the default), ``"steps"``
        (``total_steps`` env steps for the run, :attr:`steps_per_env` each) or ``"run_episodes"``
        (``total_episodes`` finished episodes for the run, all envs together)."""
        c = self.config
        return "steps" if c.total_steps else "run_episodes" if c.total_episodes else "episodes"

    @property
    def steps_per_env(self) -> int:
        """Env steps each env runs under the step budget: ``ceil(total_steps / n_envs)`` (so the run does
        ``n_envs * steps_per_env >= total_steps``, exactly ``total_steps`` when ``n_envs`` divides it)."""
        c = self.config
        return -(-c.total_steps // c.n_envs)

    @property
    def budget_total(self) -> tuple[int, str]:
        """``(amount, unit)`` the progress counts towards: episodes per env, steps per env, or episodes of the run."""
        b = self.budget
        if b == "steps":
            return self.steps_per_env, "steps"
        if b == "run_episodes":
            return self.config.total_episodes, "episodes"
        return self.config.nepisodes, "episodes"

    def _active(self, runner: Runner) -> jax.Array:
        """Which envs still learn and record in this step (``[n_envs]``), by the run's budget."""
        c, b = self.config, self.budget
        if b == "steps":
            return runner.env_steps < self.steps_per_env
        if b == "run_episodes":  # one total over the batch: every env goes on until the run has its episodes
            return jnp.broadcast_to(jnp.sum(runner.episode) < c.total_episodes, runner.episode.shape)
        return runner.episode < c.nepisodes

    def progress(self, runner: Runner) -> tuple[jax.Array, jax.Array, jax.Array]:
        """``(done, mean_last_return, useful_steps)`` of a carry (over every leading axis too: a sweep's rows):
        ``done`` in the units of :attr:`budget_total`, the fewest of any env (of any row for the run's episodes),
        the mean return of each env's last recorded episode, and the env steps that counted towards the budget
        (all envs, float32: a display figure). The driver's done test and every progress line read it."""
        b = self.budget
        if b == "steps":
            done = jnp.min(runner.env_steps)
        elif b == "run_episodes":
            done = jnp.min(jnp.sum(runner.episode, axis=-1))
        else:
            done = jnp.min(runner.episode)
        _, last = progress_stats(runner)
        return done, last, jnp.sum(runner.env_steps.astype(jnp.float32))

    # ---- building blocks -------------------------------------------------------------------------------
    def _rows(self, agent, s, envs=None):
        """Table rows ``[len(s), n_tables, n_actions]`` at states ``s``: of each env's own table (of the tables of
        ``envs``, a subset of the batch, when given), or of the shared table."""
        if self.config.shared_table:
            return jax.vmap(tabular.rows, in_axes=(None, 0))(agent, s)
        if envs is None:
            return jax.vmap(tabular.rows)(agent, s)
        return agent.q[envs, :, s, :]

    def _select(self, key, q_rows, epsilon):
        select = lambda k, r, e: self.learner.select(  # noqa: E731
            k, tabular.policy_values(r), e, self.config.seed_compat)
        return jax.vmap(select)(key, q_rows, epsilon)

    def _learn(self, key, agent, q_s, q_s2, s, a, r, s2, a2, terminated, epsilon, params, active):
        """The updated tables, and ``q_s2`` as it reads after the update (where ``s' == s`` the entry changed)."""
        c, learner = self.config, self.learner
        if c.shared_table:
            if self.plan.devices > 1:
                # Every device gets every env's transition and sums them into the one table in env order, as one
                # device would: the same table bit for bit (a sum of per-device partial tables rounds otherwise).
                key, s, a, r, s2, a2, terminated, epsilon, active = _everywhere(
                    self.plan.devices, (key, s, a, r, s2, a2, terminated, epsilon, jnp.broadcast_to(active, s.shape)))
            return tabular.learn_shared(learner, key, agent, s, a, r, s2, a2, terminated, epsilon, params,
                                        c.seed_compat, active, ordered=self.plan.ordered_sums), q_s2
        visited_sa = jax.vmap(lambda v, s, a: v[s, a])(agent.visited, s, a) if c.seed_compat else None
        table, old, new = jax.vmap(tabular.update, in_axes=(None, 0, 0, 0, 0, 0, 0, 0, 0, None, None, 0))(
            learner, key, q_s, q_s2, a, r, a2, terminated, epsilon, params, c.seed_compat, visited_sa)
        written = jnp.where(active, new, old)
        agent = jax.vmap(tabular.write)(agent, table, s, a, written, active)
        n_tables, n_actions = q_s2.shape[1:]
        hit = ((s2 == s)[:, None, None] & (jnp.arange(n_tables)[:, None] == table[:, None, None])
               & (jnp.arange(n_actions) == a[:, None, None]))
        return agent, jnp.where(hit, written[:, None, None], q_s2)

    def _reset(self, keys, env_params):
        states = jax.vmap(self.env.reset, in_axes=(0, None))(keys, env_params)
        return states, jax.vmap(self.disc)(states.obs)

    def _reset_done(self, done, keys, env_params, stepped, s2, agent, q_s2, capacity=None):
        """``(env_state, s, q_rows)`` with a fresh episode (its first state index and table rows) wherever ``done``.

        The shared autoreset (:func:`jaxrobo.task.autoreset.reset_where`): each env resets from its own key in
        ``keys``; with ``capacity`` (default ``self.reset_capacity``) below the batch size, the done envs are
        gathered, reset and scattered back (the same values as the select over the batch, tested)."""
        capacity = self.reset_capacity if capacity is None else capacity

        def fresh(keys, envs):
            states, s = self._reset(keys, env_params)
            return states, s, None if q_s2 is None else self._rows(agent, s, envs)

        return autoreset.reset_where(fresh, done, keys, (stepped, s2, q_s2), capacity)

    # ---- public ----------------------------------------------------------------------------------------
    def init(self, key: jax.Array, agent_params: AgentParams, env_params: Any = None) -> Runner:
        c = self.config
        env_params = self.env.default_params if env_params is None else env_params
        n = c.n_envs
        k_env, k_run, k_act = jax.random.split(key, 3)
        env_state, s = self._reset(jax.random.split(k_env, n), env_params)
        agent = tabular.init(self.learner, self.disc.n_states, self.n_actions, c.seed_compat)
        if not c.shared_table:
            agent = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), agent)
        epsilon = tabular.decay_epsilon(jnp.full((n,), agent_params.epsilon, jnp.float32), agent_params)
        q_rows = self._rows(agent, s)
        action = self._select(jax.random.split(k_act, n), q_rows, epsilon)
        n_rec = c.nepisodes if c.record_episodes else 1
        snapshots = jnp.broadcast_to(agent.q, (c.snapshots,) + agent.q.shape) if c.snapshots else None
        return Runner(
            env_state=env_state, agent=agent, s=s, q_rows=q_rows if self.carry_rows else None, action=action,
            epsilon=epsilon,
            episode=jnp.zeros(n, jnp.int32), ep_return=jnp.zeros(n, jnp.float32),
            key=jax.random.split(k_run, n),
            returns=jnp.zeros((n, n_rec), jnp.float32), lengths=jnp.zeros((n, n_rec), jnp.int32),
            terminated=jnp.zeros((n, n_rec), bool), nan_episodes=jnp.zeros(n, jnp.int32),
            env_steps=jnp.zeros(n, jnp.int32), snapshots=snapshots)

    @property
    def jitted_init(self) -> Any:
        """``jax.jit(self.init)``, the same object while the plan stays: JAX keeps a jitted function's trace per
        function object, so the checkpoint's template (:func:`jaxrobo.training.checkpoint.carry_template`) and the
        run's first carry (:func:`jaxrobo.training.driver.compiled_init`) trace the env's reset once. A new plan
        (assigning one of its choices) gets a new one: the trace follows the plan."""
        kept = self.__dict__.get("_jitted_init")
        if kept is None or kept[0] is not self.plan:
            kept = self.__dict__["_jitted_init"] = (self.plan, jax.jit(self.init))
        return kept[1]

    def step(self, runner: Runner, agent_params: AgentParams, env_params: Any) -> Runner:
        """One training step of every environment."""
        c, learner = self.config, self.learner
        # The five keys of ``split(key, 5)``, each hashed on its own: those a learner does not use cost nothing.
        k_next, k_act, k_act2, k_learn, k_reset = (jax.vmap(rng.subkey, in_axes=(0, None, None))(runner.key, i, 5)
                                                   for i in range(5))
        active = self._active(runner)
        q_s = self._rows(runner.agent, runner.s) if runner.q_rows is None else runner.q_rows
        a = runner.action if learner.on_policy else self._select(k_act, q_s, runner.epsilon)

        stepped = step_batch(self.env, runner.env_state, a, env_params, self.plan)
        s2 = jax.vmap(self.disc)(stepped.obs)
        done = stepped.terminated | stepped.truncated | (stepped.steps >= c.nsteps)
        q_s2 = self._rows(runner.agent, s2)  # before the update: what the targets (and Sarsa's next action) see
        a2 = self._select(k_act2, q_s2, runner.epsilon) if learner.on_policy else a
        agent, q_s2 = self._learn(k_learn, runner.agent, q_s, q_s2, runner.s, a, stepped.reward, s2, a2,
                                  stepped.terminated, runner.epsilon, agent_params, active & ~stepped.physics_nan)

        ep_return = runner.ep_return + stepped.reward
        record = done & active
        returns, lengths, terminated = runner.returns, runner.lengths, runner.terminated
        if c.record_episodes:
            # Only the envs that finished an episode write: the others' slot is out of range and their write is
            # dropped, which leaves their entry as it was without reading it first.
            if self.budget == "episodes":
                slot = jnp.where(record, jnp.minimum(runner.episode, c.nepisodes - 1), c.nepisodes)
            else:  # the first nepisodes episodes of each env are recorded; later ones are counted, not stored
                slot = jnp.where(record & (runner.episode < c.nepisodes), runner.episode, c.nepisodes)
            rows = jnp.arange(c.n_envs)
            put = lambda table, value: table.at[rows, slot].set(value, mode="drop")  # noqa: E731
            returns = put(returns, ep_return)
            lengths = put(lengths, stepped.steps)
            terminated = put(terminated, stepped.terminated)
        else:  # keep the running totals only: slot 0 holds the sum of returns and lengths
            returns = returns.at[:, 0].add(jnp.where(record, ep_return, 0.0))
            lengths = lengths.at[:, 0].add(jnp.where(record, stepped.steps, 0))
            terminated = terminated.at[:, 0].set(terminated[:, 0] | (record & stepped.terminated))

        env_state, s_next, q_rows = self._reset_done(done, k_reset, env_params, stepped, s2, agent,
                                                     None if runner.q_rows is None else q_s2)
        epsilon = jnp.where(done, tabular.decay_epsilon(runner.epsilon, agent_params), runner.epsilon)
        if learner.on_policy:
            # Used only where done: the new episode's first action, from the updated table.
            a_fresh = self._select(k_act, self._rows(agent, s_next) if q_rows is None else q_rows, epsilon)
            action = jnp.where(done, a_fresh, a2)
        else:
            action = a
        return Runner(
            env_state=env_state, agent=agent, s=s_next, q_rows=q_rows, action=action, epsilon=epsilon,
            episode=runner.episode + record.astype(jnp.int32), ep_return=jnp.where(done, 0.0, ep_return),
            key=k_next, returns=returns, lengths=lengths, terminated=terminated,
            nan_episodes=runner.nan_episodes + (record & stepped.physics_nan).astype(jnp.int32),
            env_steps=runner.env_steps + active.astype(jnp.int32), snapshots=runner.snapshots)

    def run_chunk(self, runner: Runner, agent_params: AgentParams, env_params: Any = None) -> Runner:
        """``chunk_steps`` training steps as one ``lax.scan`` (under a fused plan with ``fused_block``, one scan per
        block of envs: :meth:`run_chunk_blocked`), then the late tables kept (:meth:`keep_snapshots`)."""
        return self.keep_snapshots(self._run_steps(runner, agent_params, env_params))

    def keep_snapshots(self, runner: Runner) -> Runner:
        """The carry with snapshot k set to its table while the run's progress (:meth:`progress`'s ``done``) is at
        or before ``1 - k * SNAPSHOT_SPACING`` of the budget: after the run, the table at the last chunk boundary
        before each of those points. Unchanged without ``snapshots``."""
        if runner.snapshots is None:
            return runner
        points = jnp.asarray(self.snapshot_points())
        take = (self.progress(runner)[0] <= points).reshape((-1,) + (1,) * runner.agent.q.ndim)
        return runner.replace(snapshots=jnp.where(take, runner.agent.q[None], runner.snapshots))

    def snapshot_points(self) -> list[int]:
        """Where the snapshots are kept, in the units of :attr:`budget_total`: ``floor((1 - k * SNAPSHOT_SPACING) *
        total)`` for k = 1 .. ``snapshots`` (e.g. 285, 270, 255, 240 of 300 episodes)."""
        total = self.budget_total[0]
        # The small lift keeps a product such as 0.65 * 100 = 64.99999... at 65.
        return [int(total * (1 - k * SNAPSHOT_SPACING) + 1e-9) for k in range(1, self.config.snapshots + 1)]

    def final_table(self, runner: Runner, key: jax.Array, env_params: Any = None) -> tuple[Runner, jax.Array]:
        """The carry of a finished run with its final table chosen among the final one and the late snapshots,
        and the choice (0: the final table; k: snapshot k, the one at ``1 - k * SNAPSHOT_SPACING`` of the budget).

        Why: the last updates of a run come from the few envs still flying, and a greedy flight that loops between
        two near-tied states lowers the loop's values on every lap until another action wins there; the table
        frozen at the end keeps whichever flip came last, and its greedy policy may loop where a table a few
        chunks earlier did not (docs/quadcopter.md, "Why the run keeps the best of its late tables"). Each
        candidate flies the same ``snapshot_episodes`` greedy episodes, from ``fold_in(key, 3)`` of the run's
        ``key`` (the evaluation's are 1 and 2: :func:`jaxrobo.training.driver.evaluation_keys`), and the best by
        the task's learning target
        (:func:`jaxrobo.task.env.ranking`; a tie by the higher mean return, then the later table) is kept. Pure
        and traceable: ``jaxrobo train``, the sweep and the benchmarks' vmapped populations choose alike."""
        if runner.snapshots is None:
            return runner, jnp.int32(0)
        env_params = self.env.default_params if env_params is None else env_params
        candidates = jnp.concatenate([runner.agent.q[None], runner.snapshots])
        k = jax.random.fold_in(key, 3)
        out = jax.vmap(lambda q: self.evaluate_episodes(k, runner.agent.replace(q=q), self.config.snapshot_episodes,
                                                        env_params))(candidates)
        rank = ranking(getattr(self.env, "learning_target", None))
        figure = {"success_rate": "arrived", "mean_return": "return", "mean_length": "length"}[rank.table_metric]
        score = out[figure].astype(jnp.float32).mean(axis=1) if figure in out else None
        best = rank.best_of(score, out["return"].mean(axis=1), jnp)  # the first (latest) of the best
        return runner.replace(agent=runner.agent.replace(q=candidates[best])), best.astype(jnp.int32)

    def _run_steps(self, runner: Runner, agent_params: AgentParams, env_params: Any = None) -> Runner:
        """``chunk_steps`` training steps (:meth:`run_chunk` without the snapshots)."""
        env_params = self.env.default_params if env_params is None else env_params
        plan = self.plan
        if plan.fused == "pallas" and not physics_kernel(self.env):  # the whole chunk as the task's one kernel
            written = libdevice_sincos.written_out() if plan.fast_sincos else None
            return type(self.env).chunk_kernel.run_chunk(self, runner, agent_params, env_params, written)
        if plan.fused == "xla" and plan.fused_block is not None and not self.config.shared_table \
                and plan.fused_block < self.config.n_envs:
            # The plan's fused path: the same steps, block of envs after block (see jaxrobo.physics.fused).
            return self.run_chunk_blocked(runner, agent_params, env_params, plan.fused_block)
        body = lambda r, _: (self.step(r, agent_params, env_params), None)  # noqa: E731
        return jax.lax.scan(body, runner, None, length=self.config.chunk_steps)[0]

    def share(self, n_envs: int, plan: ExecutionPlan, **config: Any) -> "Trainer":
        """A trainer of ``n_envs`` of this trainer's envs (a block of them, or one device's) under ``plan``: the
        same env, learner and discretiser, the step budget the same per env (``total_steps`` scaled to its envs, so
        that :attr:`steps_per_env` is this trainer's), ``config`` replacing other fields."""
        c = self.config
        total = self.steps_per_env * n_envs if self.budget == "steps" else c.total_steps
        return Trainer(self.env, dataclasses.replace(c, n_envs=n_envs, total_steps=total, **config), self.disc,
                       self.learner, plan=plan)

    def _block_trainer(self, size: int) -> "Trainer":
        """A trainer for ``size`` of this trainer's envs (:meth:`share`), unfused (it is the block's body), with the
        plan's reset capacity scaled to the block."""
        c, plan = self.config, self.plan
        capacity = None
        if plan.reset_capacity is not None and plan.reset_capacity < c.n_envs:
            capacity = max(1, -(-plan.reset_capacity * size // c.n_envs))
        return self.share(size, plan.replace(fused="off", fused_block=None, reset_capacity=capacity))

    def run_chunk_blocked(self, runner: Runner, agent_params: AgentParams, env_params: Any, block: int) -> Runner:
        """``run_chunk`` with the loop over steps inside a loop over blocks of ``block`` envs (the last block
        shorter if need be): each block runs all ``chunk_steps`` steps, its carry updated in place. Only for
        per-env tables (``run_chunk`` checks): the envs are then independent and the values are the unblocked
        ones (the fused plan of :mod:`jaxrobo.physics.fused`)."""
        bodies: dict[int, Trainer] = {}

        def one_block(part: Runner) -> Runner:
            size = jax.tree.leaves(part)[0].shape[0]
            if size not in bodies:
                bodies[size] = self._block_trainer(size)
            return bodies[size].run_chunk(part, agent_params, env_params)

        # One block per loop iteration (not written out: each written-out block is another copy of the whole
        # chunk to compile).
        return map_groups(one_block, runner, block, unrolled=1)

    # ---- the learning-target stop -------------------------------------------------------------------------
    def target_every(self) -> int:
        """Chunks between learning-target checks (:func:`jaxrobo.training.driver.target_check`), counted from the
        run's start; 0: the run does not check (``stop_at_target`` off, no declared target, no evaluation episodes,
        a target the evaluation cannot measure, or a first check that would come after the run's last chunk).

        Automatic (``target_every=0``): the check's worst case (every episode flying the whole horizon) costs
        about half the training between checks, counted both in env slots and in sequential steps (a GPU's cost);
        an untrained table's short episodes end the check's flight early (it stops at the first segment boundary
        after its last episode: :class:`jaxrobo.training.driver.Flights`), so the typical check costs far less.
        A function of the config alone: the same run checks at the same chunks, whatever the device, and a
        resumed run checks where the uninterrupted one did."""
        c = self.config
        target = getattr(self.env, "learning_target", None)
        if not c.stop_at_target or target is None or not c.eval_episodes or not self._target_measurable(target):
            return 0
        every = c.target_every
        if not every:
            horizon = self.eval_horizon()
            tables = 1 if c.shared_table else min(c.eval_envs, c.n_envs)
            flights = (tables + 1) * c.eval_episodes * horizon
            ratio = max(horizon / c.chunk_steps, flights / (c.n_envs * c.chunk_steps))
            every = max(1, int(-(-TARGET_CHECK_SPACING * ratio // 1)))
        return every if every < self.max_chunks() else 0

    def _target_measurable(self, target: Any) -> bool:
        if target.metric != "success_rate":
            return True
        declared = task_fields(self.env)  # the hook's annotation; else the reset's traced shapes
        if declared is not None:
            return "arrived" in declared
        return hasattr(getattr(reset_shapes(self.env), "task", None), "arrived")

    def max_chunks(self) -> int:
        """Chunks that finish the run: exactly so under the step budget; an upper bound under the episode
        budgets (every env ends an episode at least every ``nsteps`` steps; the driver stops once the budget is
        met)."""
        c, b = self.config, self.budget
        if b == "steps":
            return -(-self.steps_per_env // c.chunk_steps)
        episodes = -(-c.total_episodes // c.n_envs) if b == "run_episodes" else c.nepisodes
        return -(-episodes * c.nsteps // c.chunk_steps)

    def evaluate(self, key: jax.Array, agent: AgentState, n_episodes: int, env_params: Any = None,
                 max_steps: int | None = None) -> tuple[jax.Array, jax.Array]:
        """Greedy episodes with one table (:func:`jaxrobo.task.rollout.rollout` of
        :func:`jaxrobo.task.rollout.greedy_policy`): ``(returns, lengths)``, each ``[n_episodes]``."""
        out = self.evaluate_episodes(key, agent, n_episodes, env_params, max_steps)
        return out["return"], out["length"]

    def evaluate_episodes(self, key: jax.Array, agent: AgentState, n_episodes: int, env_params: Any = None,
                          max_steps: int | None = None) -> dict[str, jax.Array]:
        """The episodes of :meth:`evaluate` (the same keys, so the same episodes) with how each ended, from the
        one rollout (:func:`jaxrobo.task.rollout.outcomes`)."""
        env_params = self.env.default_params if env_params is None else env_params
        return rollout.outcomes(rollout.rollout(self.env, self.eval_policy(agent), key, n_episodes,
                                                self.eval_horizon(max_steps), env_params))

    def eval_policy(self, agent: AgentState) -> rollout.Policy:
        """The greedy policy the evaluation flies with one table (ties broken at random by the step's key)."""
        return rollout.greedy_policy(agent.q, self.disc)

    def eval_horizon(self, max_steps: int | None = None) -> int:
        """The evaluation's step cap per episode: ``max_steps``, else the env spec's ``max_episode_steps``."""
        return int(max_steps or (self.env.spec.max_episode_steps if self.env.spec else 1000))


def _everywhere(devices: int, tree: Any) -> Any:
    """``tree`` replicated on the first ``devices`` devices (the run's mesh,
    :func:`jaxrobo.training.driver.env_mesh`)."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    import numpy as np

    mesh = Mesh(np.asarray(jax.devices()[:devices]), ("batch",))
    return jax.lax.with_sharding_constraint(tree, NamedSharding(mesh, PartitionSpec()))


def progress_stats(runner: Runner) -> tuple[jax.Array, jax.Array]:
    """Fewest episodes done by any env, and the mean return of each env's last finished episode (over every
    leading axis: a sweep's rows too)."""
    last_slot = jnp.clip(runner.episode - 1, 0, runner.returns.shape[-1] - 1)
    last = jnp.take_along_axis(runner.returns, last_slot[..., None], axis=-1)[..., 0]
    return jnp.min(runner.episode), jnp.mean(last)
