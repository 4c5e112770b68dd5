"""Vectorised tabular training: the seed's episodes × steps loop, for ``n_envs`` environments at once.

Each environment runs the seed's experiment with its own learner and table (or, with ``shared_table``, all of
them feed one table): ``nepisodes`` episodes of at most ``nsteps`` steps, the learner updated every step,
``epsilon *= epsilon_discount`` at the start of every episode while it is above ``epsilon_min``. Environments
that finish an episode reset with fresh randomness at once and carry on with their next episode; an
environment that has done all its episodes stops learning and recording, so the results do not depend on how
long the others take, nor on the chunk length.

The whole step (act → env step → discretise → learn → record → auto-reset) is one function scanned over
``chunk_steps`` steps and jitted once; the host only runs chunk after chunk and reads a few numbers in between
for the progress bar, so the hot loop never syncs with the host. ``init`` and ``run_chunk`` take the learner
and env parameters as arguments, so a sweep vmaps them over a configuration axis (:mod:`jaxrobo.sweep`).

The host loop (:func:`train`) starts from a fresh carry or a saved one (:func:`save_checkpoint` /
:func:`load_checkpoint`, what ``jaxrobo train --resume`` uses), hands the carry to a checkpoint callback now and
then, and stops at a chunk boundary when asked.
"""
from __future__ import annotations

import dataclasses
import json
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from agents import tabular
from agents.tabular import AgentParams, AgentState, Learner
from jaxrobo import autoreset, budget, registry, rng, rollout, rundir
from jaxrobo.config import flat_keys
from jaxrobo.discretise import MODES, Discretiser, make_discretiser
from jaxrobo.env import Env, EnvState, LearningTarget
from jaxrobo.plan import ExecutionPlan, step_batch
from jaxrobo.struct import param, pytree_dataclass


@pytree_dataclass
class TrainConfig:
    """How a run is shaped (static: these fix array shapes and code paths)."""

    agent: str = param("qlearn", choices=tuple(registry.learners()), static=True, doc="tabular learner")
    n_envs: int = param(64, low=1, static=True, doc="independent copies of the experiment run at once")
    nepisodes: int = param(1000, low=1, static=True, doc="episodes per environment")
    nsteps: int = param(1000, low=1, static=True, doc="step cap per episode in the training loop")
    seed: int = param(0, low=0, static=True, doc="random seed; the same seed gives the same results")
    seed_compat: bool = param(False, static=True, doc="reproduce the seed's learners exactly (SPEC §4)")
    shared_table: bool = param(False, static=True, doc="one table learning from all environments")
    discretiser: str = param("bins", choices=MODES, static=True, doc="how observations become states")
    number_splits: int = param(10, low=1, high=10_000, static=True, doc="bins per observation dimension")
    bins: tuple | None = param(None, kind=tuple, static=True, doc="bins per dimension (overrides number_splits)")
    state_low: tuple | None = param(None, kind=tuple, static=True, doc="discretiser lower bounds (default: task's)")
    state_high: tuple | None = param(None, kind=tuple, static=True, doc="discretiser upper bounds")
    edges: tuple | None = param(None, kind=tuple, static=True, doc="interior bin edges per dimension (mode edges)")
    resolution: float = param(0.1, low=0.0, low_open=True, static=True, doc="bin width of mode round")
    chunk_steps: int = param(1000, low=1, static=True, doc="steps per compiled chunk between progress updates")
    record_episodes: bool = param(True, static=True, doc="keep every episode's return and length")
    eval_episodes: int = param(100, low=0, static=True, doc="greedy evaluation episodes per evaluated table")
    eval_envs: int = param(8, low=1, static=True, doc="how many trained tables to evaluate")
    env_group: int = param(0, low=0, static=True,
                           doc="envs stepped together, group after group (0: automatic, see ExecutionPlan)")


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


def make_discretiser_for(env: Env, config: TrainConfig, env_params: Any = None) -> Discretiser:
    """The discretiser a config asks for, over the task's state bounds unless the config gives its own."""
    low, high = env.state_bounds(env_params)
    low = np.asarray(config.state_low if config.state_low is not None else low, np.float64)
    high = np.asarray(config.state_high if config.state_high is not None else high, np.float64)
    splits = config.bins if config.bins is not None else config.number_splits
    return make_discretiser(low, high, config.discretiser, splits, config.resolution, config.edges)


class Trainer:
    """Pure ``init`` / ``run_chunk`` / ``evaluate`` for one env, learner, discretiser and config."""

    def __init__(self, env: Env, config: TrainConfig, discretiser: Discretiser | None = None,
                 learner: Learner | None = None, *, plan: ExecutionPlan | None = None):
        """``plan``: how the run is executed (:class:`jaxrobo.plan.ExecutionPlan`; default: the plan for this env
        and config on the default device). It changes the compiled program, never the values."""
        self.env = env
        self.config = config
        self.learner = learner or registry.learner(config.agent)
        self.disc = discretiser or make_discretiser_for(env, config)
        self.n_actions = env.num_actions
        self.plan = ExecutionPlan.for_run(env, config) if plan is None else plan
        if config.shared_table and self.learner.n_tables > 1 and config.seed_compat:
            raise ValueError("seed_compat applies to one-table learners; double_q has no seed form")

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
        select = lambda k, r, e: self.learner.select(k, tabular.policy_values(r), e, self.config.seed_compat)  # noqa: E731
        return jax.vmap(select)(key, q_rows, epsilon)

    def _learn(self, key, agent, q_s, q_s2, s, a, r, s2, a2, terminated, epsilon, params, active):
        """The updated tables, and ``q_s2`` as it reads after the update (where ``s' == s`` the entry changed)."""
        c, learner = self.config, self.learner
        if c.shared_table:
            return tabular.learn_shared(learner, key, agent, s, a, r, s2, a2, terminated, epsilon, params,
                                        c.seed_compat, active), q_s2
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

        The shared autoreset (:func:`jaxrobo.autoreset.reset_where`): each env resets from its own key in
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
        return Runner(
            env_state=env_state, agent=agent, s=s, q_rows=q_rows if self.carry_rows else None, action=action,
            epsilon=epsilon,
            episode=jnp.zeros(n, jnp.int32), ep_return=jnp.zeros(n, jnp.float32),
            key=jax.random.split(k_run, n),
            returns=jnp.zeros((n, n_rec), jnp.float32), lengths=jnp.zeros((n, n_rec), jnp.int32),
            terminated=jnp.zeros((n, n_rec), bool), nan_episodes=jnp.zeros(n, jnp.int32),
            env_steps=jnp.zeros(n, jnp.int32))

    def step(self, runner: Runner, agent_params: AgentParams, env_params: Any) -> Runner:
        """One training step of every environment."""
        c, learner = self.config, self.learner
        # The five keys of ``split(key, 5)``, each hashed on its own: those a learner does not use cost nothing.
        k_next, k_act, k_act2, k_learn, k_reset = (jax.vmap(rng.subkey, in_axes=(0, None, None))(runner.key, i, 5)
                                                   for i in range(5))
        active = runner.episode < c.nepisodes
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
            slot = jnp.minimum(runner.episode, c.nepisodes - 1)
            rows = jnp.arange(c.n_envs)
            put = lambda table, value: table.at[rows, slot].set(jnp.where(record, value, table[rows, slot]))  # noqa: E731
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
            env_steps=runner.env_steps + active.astype(jnp.int32))

    def run_chunk(self, runner: Runner, agent_params: AgentParams, env_params: Any = None) -> Runner:
        """``chunk_steps`` training steps as one ``lax.scan``."""
        env_params = self.env.default_params if env_params is None else env_params
        body = lambda r, _: (self.step(r, agent_params, env_params), None)  # noqa: E731
        return jax.lax.scan(body, runner, None, length=self.config.chunk_steps)[0]

    def max_chunks(self) -> int:
        c = self.config
        return -(-c.nepisodes * c.nsteps // c.chunk_steps)

    def evaluate(self, key: jax.Array, agent: AgentState, n_episodes: int, env_params: Any = None,
                 max_steps: int | None = None) -> tuple[jax.Array, jax.Array]:
        """Greedy episodes with one table (:func:`jaxrobo.rollout.rollout` of
        :func:`jaxrobo.rollout.greedy_policy`): ``(returns, lengths)``, each ``[n_episodes]``."""
        env_params = self.env.default_params if env_params is None else env_params
        horizon = int(max_steps or (self.env.spec.max_episode_steps if self.env.spec else 1000))
        out = rollout.rollout(self.env, rollout.greedy_policy(agent.q, self.disc), key, n_episodes, horizon,
                              env_params)
        return out["return"], out["length"]


@dataclasses.dataclass
class TrainResult:
    """What a run produced, as host arrays, with the seed's summary figures."""

    env_id: str
    config: TrainConfig
    agent_params: AgentParams
    returns: np.ndarray  # [n_envs, nepisodes]
    lengths: np.ndarray
    terminated: np.ndarray
    epsilon: np.ndarray  # [nepisodes]
    nan_episodes: np.ndarray  # [n_envs]
    env_steps: int
    q: np.ndarray  # [n_envs or 1, n_tables, n_states, n_actions]
    compile_seconds: float
    run_seconds: float
    eval_returns: np.ndarray | None = None  # [eval_envs, eval_episodes]
    eval_lengths: np.ndarray | None = None
    selected: dict[str, Any] | None = None  # the best evaluated table, re-evaluated on fresh episodes
    #: False when ``should_stop`` ended the run early: the records hold the episodes finished so far
    #: (``episodes_done`` per env), there is no evaluation, and the carry at ``chunks_done`` goes on from there.
    complete: bool = True
    chunks_done: int = 0
    episodes_done: np.ndarray | None = None  # [n_envs] finished episodes per env
    #: The task's declared target (:class:`jaxrobo.env.LearningTarget`; None: no target), for :meth:`summary`.
    learning_target: LearningTarget | None = None
    plan: str | None = None  # repr of the run's ExecutionPlan (how it ran; the values do not depend on it)

    @property
    def steps_per_second(self) -> float:
        return self.env_steps / max(self.run_seconds, 1e-9)

    def summary(self) -> dict[str, Any]:
        """The seed's figures (highest cumulated reward, overall mean length, mean of the best 100), per run, and
        how many evaluated tables reach the task's declared learning target (``learning_target``)."""
        lengths = self.lengths.astype(np.float64)
        best100 = np.sort(lengths, axis=1)[:, -100:].mean(axis=1)
        out = {
            "env_id": self.env_id,
            "agent": self.config.agent,
            "n_envs": self.config.n_envs,
            "nepisodes": self.config.nepisodes,
            "highest_reward_mean": float(self.returns.max(axis=1).mean()),
            "highest_reward_max": float(self.returns.max()),
            "overall_mean_length": float(lengths.mean()),
            "best_100_mean_length": float(best100.mean()),
            "final_100_mean_return": float(self.returns[:, -100:].mean()),
            "physics_nan_episodes": int(self.nan_episodes.sum()),
            "env_steps": int(self.env_steps),
            "compile_seconds": round(self.compile_seconds, 3),
            "run_seconds": round(self.run_seconds, 3),
            "env_steps_per_second": round(self.steps_per_second, 1),
        }
        target = self.learning_target
        if target is not None:
            out["learning_target"] = target.description
        if self.plan is not None:
            out["execution_plan"] = self.plan
        if self.eval_lengths is not None and self.eval_lengths.size:
            out["eval_mean_length"] = float(self.eval_lengths.mean())
            out["eval_mean_return"] = float(self.eval_returns.mean())
            out["eval_best_table_mean_length"] = float(self.eval_lengths.mean(axis=1).max())
            per_table = {"mean_length": self.eval_lengths, "mean_return": self.eval_returns}
            if target is not None and target.metric in per_table:
                score = per_table[target.metric].astype(np.float64).mean(axis=1)
                out[f"eval_share_of_tables_{target.name}"] = float((score >= target.threshold).mean())
        if self.selected is not None:
            out["selected_table"] = self.selected["table"]
            out["selected_table_fresh_mean_length"] = float(self.selected["lengths"].mean())
            out["selected_table_fresh_mean_return"] = float(self.selected["returns"].mean())
        return out


ProgressFn = Callable[[int, int, float], None]


def _compiled_chunk(trainer: Trainer, runner: Runner, agent_params: AgentParams, env_params: Any) -> Callable:
    """``trainer.run_chunk`` traced, lowered and compiled for ``runner``.

    Traced afresh in every process and every call, under the trainer's plan (its compiler options, its
    trace-time choices), so training runs the code as it is now in this process (a patched physics step, another
    plan), exactly as evaluation does. A second start of the same configuration still skips XLA: the persistent
    compilation cache (:mod:`jaxrobo.cache`) is keyed on the lowered module, so it serves the executable only
    when the traced program is the same."""
    plan = trainer.plan
    with plan.tracing():
        return jax.jit(trainer.run_chunk, donate_argnums=0, compiler_options=plan.xla_options).lower(
            runner, agent_params, env_params).compile()


CheckpointFn = Callable[[Runner, int], None]


def train(env: Env, config: TrainConfig, agent_params: AgentParams | None = None, env_params: Any = None,
          progress: ProgressFn | None = None, *, initial: Runner | None = None, start_chunk: int = 0,
          checkpoint: CheckpointFn | None = None, checkpoint_every: int = 0,
          checkpoint_seconds: float | None = None, should_stop: Callable[[], bool] | None = None,
          plan: ExecutionPlan | None = None) -> TrainResult:
    """Run a whole training; ``progress(episodes_done_min, nepisodes, mean_last_return)`` after each chunk.

    The host loop runs chunk after chunk from ``initial`` (a carry after ``start_chunk`` chunks, e.g. from
    :func:`load_checkpoint`; default: a fresh ``Trainer.init``), so a resumed run is the uninterrupted one bit for
    bit: training is deterministic and does not depend on where the chunks are cut. ``initial`` is donated to
    the first chunk (its buffers are reused).

    ``checkpoint(runner, chunks_done)`` is called with the carry every ``checkpoint_every`` chunks and/or at the
    first chunk boundary ``checkpoint_seconds`` after the last one (neither: never), except after the last chunk,
    and when ``should_stop()`` says to stop: that is asked before each chunk, so a stop request finishes the
    current chunk, saves it through ``checkpoint`` and returns a result with ``complete=False`` (episodes so
    far, no evaluation). The library installs no signal handlers; the CLI's ``should_stop`` reads a flag its
    SIGINT/SIGTERM handlers set. Evaluation runs only after the last chunk.

    ``plan``: how the run is executed (default: :meth:`jaxrobo.plan.ExecutionPlan.for_run` of this env and
    config); everything the run traces, training chunks and evaluation, is traced under it."""
    trainer = Trainer(env, config, plan=plan)
    with trainer.plan.tracing():
        return _train(trainer, agent_params, env_params, progress, initial, start_chunk, checkpoint,
                      checkpoint_every, checkpoint_seconds, should_stop)


def _train(trainer: Trainer, agent_params: AgentParams | None, env_params: Any, progress: ProgressFn | None,
           initial: Runner | None, start_chunk: int, checkpoint: CheckpointFn | None, checkpoint_every: int,
           checkpoint_seconds: float | None, should_stop: Callable[[], bool] | None) -> TrainResult:
    """:func:`train`'s body, run inside the plan's tracing block."""
    env, config = trainer.env, trainer.config
    agent_params = agent_params or AgentParams()
    env_params = env.default_params if env_params is None else env_params
    # The CLI checked this in ``run.resolve``; a Python caller gets the same refusal before anything compiles.
    budget.check_memory(env, config, trainer.disc.n_states, where=env.name)
    key = jax.random.key(config.seed)
    t0 = time.perf_counter()
    runner = jax.jit(trainer.init)(key, agent_params, env_params) if initial is None else initial
    chunk = _compiled_chunk(trainer, runner, agent_params, env_params)
    stats = jax.jit(_progress_stats).lower(runner).compile()
    done_min = float(jax.device_get(stats(runner))[0])
    compile_seconds = time.perf_counter() - t0

    t0 = last_saved = time.perf_counter()
    n_chunks, chunks_done, stopped = trainer.max_chunks(), start_chunk, False
    while chunks_done < n_chunks and done_min < config.nepisodes:
        if should_stop is not None and should_stop():
            stopped = True
            break
        runner = chunk(runner, agent_params, env_params)
        chunks_done += 1
        done_min, last = (float(x) for x in jax.device_get(stats(runner)))
        if progress is not None:
            progress(int(done_min), config.nepisodes, last)
        finished = done_min >= config.nepisodes or chunks_done >= n_chunks
        due = (checkpoint_every > 0 and chunks_done % checkpoint_every == 0) or (
            checkpoint_seconds is not None and time.perf_counter() - last_saved >= checkpoint_seconds)
        if checkpoint is not None and due and not finished:
            checkpoint(runner, chunks_done)
            last_saved = time.perf_counter()
    jax.block_until_ready(runner)
    run_seconds = time.perf_counter() - t0
    if stopped and checkpoint is not None:
        checkpoint(runner, chunks_done)

    eval_returns = eval_lengths = selected = None
    if config.eval_episodes > 0 and not stopped:
        n_eval = min(config.eval_envs, config.n_envs) if not config.shared_table else 1
        tables = runner.agent if config.shared_table else jax.tree.map(lambda x: x[:n_eval], runner.agent)
        evaluate = jax.jit(jax.vmap(trainer.evaluate, in_axes=(0, 0 if not config.shared_table else None, None, None)),
                           static_argnums=2)
        keys = jax.random.split(jax.random.fold_in(key, 1), n_eval)
        eval_returns, eval_lengths = (np.asarray(x) for x in evaluate(keys, tables, config.eval_episodes, env_params))
        if n_eval > 1:
            # Population selection, measured honestly: the best table on the episodes above is evaluated again on
            # fresh episodes, so its figure is not the maximum of noisy estimates.
            best = int(np.argmax(eval_returns.mean(axis=1)))
            table = jax.tree.map(lambda x: x[best], tables)
            sel_returns, sel_lengths = jax.jit(trainer.evaluate, static_argnums=2)(
                jax.random.fold_in(key, 2), table, config.eval_episodes, env_params)
            selected = {"table": best, "returns": np.asarray(sel_returns), "lengths": np.asarray(sel_lengths)}

    host = jax.device_get(runner.replace(key=None, env_state=None))
    q = np.asarray(host.agent.q)
    return TrainResult(
        env_id=env.name, config=config, agent_params=agent_params,
        returns=np.asarray(host.returns), lengths=np.asarray(host.lengths), terminated=np.asarray(host.terminated),
        epsilon=tabular.epsilon_schedule(agent_params, config.nepisodes), nan_episodes=np.asarray(host.nan_episodes),
        env_steps=int(np.asarray(host.env_steps, np.int64).sum()), q=q if not config.shared_table else q[None],
        compile_seconds=compile_seconds, run_seconds=run_seconds, eval_returns=eval_returns, eval_lengths=eval_lengths,
        selected=selected, complete=not stopped, chunks_done=chunks_done,
        episodes_done=np.minimum(np.asarray(host.episode), config.nepisodes),
        learning_target=getattr(env, "learning_target", None), plan=repr(trainer.plan))


# ---- checkpoints -------------------------------------------------------------------------------------------------
#: Bumped when the checkpoint layout changes.
CHECKPOINT_FORMAT = 1


def _is_key(x: Any) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def carry_template(trainer: Trainer, agent_params: AgentParams, env_params: Any = None) -> Runner:
    """The carry's structure, shapes and dtypes (``ShapeDtypeStruct`` leaves), traced without compiling."""
    env_params = trainer.env.default_params if env_params is None else env_params
    return jax.eval_shape(trainer.init, jax.random.key(trainer.config.seed), agent_params, env_params)


def carry_fingerprint(template: Runner, run_config: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint must match to be loaded: the resolved run config, the jaxrobo and JAX versions, the
    carry's tree structure and leaf shapes/dtypes, and the hash of the sources (:func:`jaxrobo.rundir.source_hash`)."""
    import jaxrobo

    leaves, treedef = jax.tree.flatten(template)
    return json.loads(json.dumps({
        "format": CHECKPOINT_FORMAT, "config": run_config, "jaxrobo": jaxrobo.__version__, "jax": jax.__version__,
        "treedef": str(treedef), "leaves": [[list(x.shape), str(x.dtype)] for x in leaves],
        "sources": rundir.source_hash()}))


def save_checkpoint(path: str, runner: Runner, chunks_done: int, fingerprint: dict[str, Any]) -> None:
    """Write the whole training carry to ``path`` (``.npz``), atomically.

    Layout (``np.savez``, no pickled objects, so ``np.load(allow_pickle=False)`` reads it): ``leaf_<i>`` the
    i-th leaf of ``jax.tree.flatten(runner)`` as a plain array (a PRNG key array as its ``jax.random.key_data``),
    ``key_impls`` a JSON list with each leaf's PRNG implementation name or null, ``chunks_done`` the number of
    chunks the carry has run, and ``fingerprint`` the JSON of :func:`carry_fingerprint`.

    Why npz rather than orbax-checkpoint: the carry is one single-host pytree of a few arrays, written now and
    then as a whole; npz does that with numpy alone, while orbax is a heavy dependency (tensorstore, async
    managers, a directory layout per step) that is not installed here and brings nothing a single host needs."""
    from jaxrobo.rundir import atomic_savez

    leaves = jax.tree.leaves(runner)
    impls = [str(jax.random.key_impl(x)) if _is_key(x) else None for x in leaves]
    host = jax.device_get([jax.random.key_data(x) if _is_key(x) else x for x in leaves])
    arrays = {f"leaf_{i}": np.asarray(x) for i, x in enumerate(host)}
    atomic_savez(path, **arrays, key_impls=np.array(json.dumps(impls)), chunks_done=np.int64(chunks_done),
                 fingerprint=np.array(json.dumps(fingerprint, sort_keys=True)))


def read_fingerprint(path: str) -> tuple[dict[str, Any], int]:
    """A checkpoint's fingerprint and chunk count, without loading the carry."""
    with np.load(path, allow_pickle=False) as data:
        return json.loads(str(data["fingerprint"])), int(data["chunks_done"])


def fingerprint_mismatch(saved: dict[str, Any], expected: dict[str, Any]) -> str | None:
    """Why a checkpoint with fingerprint ``saved`` cannot go on as ``expected`` (None if it can)."""
    what = {"format": "checkpoint format", "config": "configuration", "jaxrobo": "jaxrobo version",
            "jax": "JAX version", "treedef": "training carry structure", "leaves": "training carry shapes/dtypes",
            "sources": "jaxrobo/envs/agents source code"}
    for field, name in what.items():
        if saved.get(field) != expected.get(field):
            if field == "config":
                a, b = flat_keys(saved.get("config") or {}), flat_keys(expected.get("config") or {})
                keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
                diff = ", ".join(f"{k}: {a.get(k)!r} in the checkpoint vs {b.get(k)!r} now" for k in keys[:5])
                return f"the configuration differs ({diff})"
            if field in ("jaxrobo", "jax"):
                return f"it was written by {name} {saved.get(field)} (this is {expected.get(field)})"
            return f"the {name} differs from the one that wrote it"
    return None


class CheckpointError(ValueError):
    """A checkpoint that cannot be loaded: unreadable, or from another config or code version."""


def load_checkpoint(path: str, template: Runner, fingerprint: dict[str, Any]) -> tuple[Runner, int]:
    """The carry saved at ``path`` and its chunk count, on the default device, checked against ``fingerprint``
    (:func:`carry_fingerprint` of this run) and ``template``'s structure: refused with :class:`CheckpointError`
    saying why, rather than loaded, when they differ."""
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise CheckpointError(f"{path}: cannot read the checkpoint ({err})") from err
    with data:
        try:
            saved = json.loads(str(data["fingerprint"]))
            impls = json.loads(str(data["key_impls"]))
            chunks_done = int(data["chunks_done"])
        except (KeyError, ValueError) as err:
            raise CheckpointError(f"{path}: not a jaxrobo checkpoint ({err})") from err
        why = fingerprint_mismatch(saved, fingerprint)
        if why is not None:
            raise CheckpointError(f"{path}: refusing to resume: {why}")
        specs, treedef = jax.tree.flatten(template)
        leaves = []
        for i, (spec, impl) in enumerate(zip(specs, impls)):
            x = data[f"leaf_{i}"]
            leaf = jax.random.wrap_key_data(x, impl=impl) if impl is not None else jnp.asarray(x)
            if leaf.shape != spec.shape or leaf.dtype != spec.dtype:
                raise CheckpointError(f"{path}: leaf {i} is {leaf.shape} {leaf.dtype}, expected {spec.shape} "
                                      f"{spec.dtype}")
            leaves.append(leaf)
    return jax.tree.unflatten(treedef, leaves), chunks_done


def _progress_stats(runner: Runner) -> tuple[jax.Array, jax.Array]:
    """Fewest episodes done by any env, and the mean return of each env's last finished episode."""
    last_slot = jnp.clip(runner.episode - 1, 0, runner.returns.shape[1] - 1)
    last = jnp.take_along_axis(runner.returns, last_slot[:, None], axis=1)[:, 0]
    return jnp.min(runner.episode), jnp.mean(last)
