"""Training with Brax's trainers (:func:`train`, :class:`DeepResult`, :class:`TrainingStopped`) and the run's own
evaluation of the deterministic policy on fresh episodes of the jaxrobo env (:func:`evaluate`)."""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, Callable, Mapping

import numpy as np

from jaxrobo.deep.config import DeepRunSpec, SACConfig
from jaxrobo.deep.policy import _factory, _networks, env_policy, network_config


# ---- evaluation ----------------------------------------------------------------------------------------------------
def evaluate(env: Any, benv: Any, net: Mapping[str, Any], n_episodes: int, horizon: int) -> Callable:
    """A ``(params, key) -> dict`` of ``n_episodes`` fresh episodes of the deterministic policy of the networks
    ``net`` (:func:`jaxrobo.deep.policy.network_config`, the trainer's own) on the jaxrobo env
    (:func:`jaxrobo.task.rollout.rollout`): ``return``, ``length``, ``terminated`` and, for a task with an
    ``arrived`` flag, ``success``. Compiled on its first call; where the process reuses traces
    (:mod:`jaxrobo.speed.reuse`), through a kept export of it (a warm run traced it in every process: 1.2 s on an
    H200 for QuadcopterGotoTwist-v0)."""
    import jax

    from jaxrobo.speed import reuse
    from jaxrobo.speed.plan import ExecutionPlan
    from jaxrobo.task.rollout import outcomes, rollout

    # The step limit of training (the wrapper's episode_length) is the evaluation's too.
    env_params = benv.params.replace(max_episode_steps=horizon)
    make_policy = _networks(net)[1]

    def run(params, key_data):
        key = jax.random.wrap_key_data(key_data)
        res = outcomes(rollout(env, env_policy(benv, make_policy, params), key, n_episodes, horizon, env_params))
        if "arrived" in res:
            res["success"] = res.pop("arrived")
        return res

    # The default plan: the trace choices every other program of a deep run is traced under.
    plan = ExecutionPlan(reuse_traces=reuse.available())
    compiled: list[Callable] = []

    def call(params, key):
        args = (params, jax.random.key_data(key))
        if not compiled:
            compiled.append(reuse.compile_reusing(plan, "deep_evaluation", run, args,
                                                  (env, benv, dict(net), n_episodes, horizon, env_params)))
        return compiled[0](*args)

    return call


# ---- training ----------------------------------------------------------------------------------------------------
#: Folded into the seed's key to derive the trainer's per-epoch keys (:func:`epoch_key`).
_EPOCH_STREAM = 0x65706F63


@dataclasses.dataclass(frozen=True)
class EpochPlan:
    """How Brax's trainer divides a run of ``config``: ``epochs`` training epochs (an evaluation point before the
    first and after each), each of ``steps_per_epoch`` env steps, after SAC's ``prefill_steps`` of random actions
    filling the replay buffer. ``total_steps`` is what the run really steps (``config.total_steps`` rounded up to
    whole epochs, as Brax does).

    Brax runs an epoch as one compiled call; jaxrobo asks it for ``chunks`` shorter ones per epoch (host
    iterations of ``unit_steps`` env steps each, a whole number of the trainer's training steps of ``step_size``
    env steps), with the random keys the whole epoch would have carried (:func:`chunk_keys`): the same
    numbers, handed back to the host often enough that a run can stop, and keep its state, between evaluation
    points."""

    epochs: int
    steps_per_epoch: int
    prefill_steps: int = 0
    #: Whether the trainer hands back control before its first epoch (an evaluation point at 0 steps): PPO always,
    #: SAC only with ``num_evals > 1``.
    initial_point: bool = True
    #: Env steps of one of the trainer's training steps (PPO: batch_size x unroll_length x num_minibatches x
    #: action_repeat; SAC: num_envs x action_repeat).
    step_size: int = 1
    #: Host iterations per epoch.
    chunks: int = 1

    def points(self, epochs_done: int) -> int:
        """Evaluation points reached after ``epochs_done`` epochs."""
        return epochs_done + int(self.initial_point)

    @property
    def total_steps(self) -> int:
        return self.prefill_steps + self.epochs * self.steps_per_epoch

    @property
    def unit_steps(self) -> int:
        """Env steps of one host iteration."""
        return self.steps_per_epoch // self.chunks

    def env_steps(self, epochs_done: int, chunks_done: int = 0) -> int:
        """Env steps of the run after ``epochs_done`` epochs and ``chunks_done`` host iterations of the next."""
        return self.prefill_steps + epochs_done * self.steps_per_epoch + chunks_done * self.unit_steps

    def trainer_budget(self, epochs_done: int, chunks_done: int = 0) -> tuple[int, int]:
        """``(num_timesteps, num_evals)`` that make Brax's trainer run what is left after ``epochs_done`` epochs
        and ``chunks_done`` host iterations of the next, as host iterations of :attr:`unit_steps` (Brax derives
        its epoch size from these two)."""
        left = (self.epochs - epochs_done) * self.chunks - chunks_done
        return self.prefill_steps + left * self.unit_steps, left + 1


def _chunks(steps: int, grain: int) -> int:
    """The fewest host iterations that split ``steps`` training steps evenly with at most ``grain`` of them each."""
    return next(k for k in range(1, steps + 1) if steps % k == 0 and steps // k <= max(grain, 1))


def epoch_plan(c: Any) -> EpochPlan:
    """The :class:`EpochPlan` of a PPO or SAC config: Brax's own arithmetic (``ppo.train``: epochs of
    ``ceil(num_timesteps / (epochs * batch_size * unroll_length * num_minibatches * action_repeat))`` training
    steps; ``sac.train``: a prefill of ``ceil(min_replay_size / num_envs)`` actor steps, then epochs of
    ``ceil((num_timesteps - prefill) / (epochs * num_envs * action_repeat))`` actor steps), each epoch in host
    iterations of at most the config's ``iteration_steps`` env steps (or one training step, if that is
    more): where the run can stop and keep its state between evaluation points."""
    epochs = max(c.num_evals - 1, 1)
    if c.agent == "ppo":
        per_step = c.batch_size * c.unroll_length * c.num_minibatches * c.action_repeat
        n = -(-c.total_steps // (epochs * per_step))
        return EpochPlan(epochs, n * per_step, step_size=per_step, chunks=_chunks(n, c.iteration_steps // per_step))
    per_step = c.action_repeat * c.num_envs
    prefill = -(-c.min_replay_size // c.num_envs) * per_step
    n = -(-(c.total_steps - prefill) // (epochs * per_step))
    return EpochPlan(epochs, n * per_step, prefill, initial_point=c.num_evals > 1, step_size=per_step,
                     chunks=_chunks(n, c.iteration_steps // per_step))


def epoch_key(seed: int, epoch: int) -> Any:
    """The raw ``uint32[2]`` key of the run's ``epoch``-th training epoch (from 0): a function of the seed and the
    epoch's index alone, so a resumed run draws the keys the uninterrupted run would have."""
    import jax

    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), _EPOCH_STREAM), epoch)


def chunk_keys(c: Any, plan: EpochPlan, chunk: int, n_devices: int) -> Any:
    """The per-device keys of the run's ``chunk``-th host iteration (from 0): those its epoch's training steps
    carry at that point (:func:`jaxrobo.interop.brax_compat.advance_epoch_keys`), so the numbers do not depend on
    how an epoch is cut into host iterations."""
    import jax

    from jaxrobo.interop.brax_compat import advance_epoch_keys

    epoch, part = divmod(chunk, plan.chunks)
    keys = jax.random.split(epoch_key(c.seed, epoch), n_devices)
    return advance_epoch_keys(c.agent, keys, part * plan.unit_steps // plan.step_size)


@dataclasses.dataclass
class Point:
    """An evaluation point the run has reached (what :func:`train` hands ``on_point``): the run's evaluations and
    Brax's training metrics so far, the epochs done of the plan, the trainer's state after the last epoch (device
    arrays, valid only during the call; None before the first epoch) and the parameters evaluated (host)."""

    spec: DeepRunSpec
    net: dict[str, Any]
    plan: EpochPlan
    epochs_done: int
    evaluations: list[dict[str, Any]]
    training_metrics: list[dict[str, float]]
    states: Any
    params: Any
    #: Training wall time of the whole run so far (all sessions, compile included, evaluations excluded).
    train_seconds: float
    #: Env steps the run had when this session started (0, or where a resumed run went on from).
    session_start_steps: int
    #: Training wall time of the run when this session started.
    session_start_seconds: float
    #: Host iterations done of the epoch after ``epochs_done`` (0 at an evaluation point; then ``params`` is None
    #: and ``train_seconds`` is the time of the iteration's end).
    chunks_done: int = 0
    #: Brax's training metrics of those host iterations (what the epoch's metrics will be made of).
    partial_metrics: list[dict[str, float]] = dataclasses.field(default_factory=list)

    @property
    def env_steps(self) -> int:
        return self.plan.env_steps(self.epochs_done, self.chunks_done)

    @property
    def row(self) -> dict[str, Any]:
        return self.evaluations[-1]


@dataclasses.dataclass
class DeepResult:
    """What a deep run produced (host values)."""

    spec: DeepRunSpec
    params: Any
    net: dict[str, Any]
    #: One dict per evaluation: ``env_steps``, ``seconds`` (training wall time so far, compile included, the
    #: evaluations excluded, over all sessions of a resumed run) and the episodes' ``return``/``length``/
    #: ``terminated`` (and ``success``) arrays.
    evaluations: list[dict[str, Any]]
    #: Brax's training metrics at each evaluation point after the first (losses, ``training/sps``, ...).
    training_metrics: list[dict[str, float]]
    seconds: float  # wall time of this session's trainer call, compile and evaluations included
    eval_seconds: float  # of which the evaluations
    #: Training wall time of the whole run (all sessions, compile included, evaluations excluded).
    train_seconds: float = 0.0
    #: Env steps done before this session (a resumed run), else 0.
    resumed_after_env_steps: int = 0
    #: Env steps at the evaluation point that met the learning target and ended the run (``stop_at_target``),
    #: else None.
    target_met_at: int | None = None
    #: A stop was asked at the last evaluation point (during the final evaluation): the training was complete.
    stopped_at_end: bool = False

    @property
    def env_steps(self) -> int:
        return int(self.evaluations[-1]["env_steps"]) if self.evaluations else 0

    def summary(self) -> dict[str, Any]:
        c = self.spec.config
        last = self.evaluations[-1]
        out: dict[str, Any] = {
            "env_id": self.spec.env_id, "agent": c.agent, "preset": self.spec.preset,
            "num_envs": c.num_envs, "total_steps": c.total_steps, "env_steps": self.env_steps,
            "episode_length": self.spec.episode_length,
            "train_seconds": round(self.train_seconds, 3), "eval_seconds": round(self.eval_seconds, 3),
            "env_steps_per_second": round(self.env_steps / max(self.train_seconds, 1e-9), 1),
            "evaluations": len(self.evaluations), "eval_episodes": c.eval_episodes,
            "final_eval_mean_return": float(np.mean(last["return"])),
            "final_eval_mean_length": float(np.mean(last["length"])),
            "best_eval_mean_return": float(max(np.mean(e["return"]) for e in self.evaluations)),
            "best_evaluation": best_index(self.evaluations, getattr(self.spec.env, "learning_target", None)),
        }
        if self.resumed_after_env_steps:
            out["resumed_after_env_steps"] = self.resumed_after_env_steps
        sps = [m["training/sps"] for m in self.training_metrics if "training/sps" in m]
        if sps:
            out["training_sps_last_epoch"] = round(float(sps[-1]), 1)
        if "success" in last:
            rates = [float(np.mean(e["success"])) for e in self.evaluations]
            out["final_eval_success_rate"] = rates[-1]
            out["best_eval_success_rate"] = max(rates)
        target = getattr(self.spec.env, "learning_target", None)
        if target is not None:
            out["learning_target"] = target.description
            out["target_met_in_training"] = self.target_met_at is not None
            if self.target_met_at is not None:
                out["target_met_at_env_steps"] = int(self.target_met_at)
                out["target_met_at_train_seconds"] = round(float(self.evaluations[-1]["seconds"]), 3)
        return out


def best_index(evaluations: list[dict[str, Any]], target: Any = None) -> int:
    """The best evaluation: for a task with a learning ``target``, the best by it
    (:meth:`jaxrobo.task.env.Ranking.best_table` over the evaluations: its metric in its direction, a tie broken
    by the higher mean return); without one, the highest success rate (a task with one), then the highest mean
    return. The earliest of equals."""
    if target is not None:
        from jaxrobo.task.env import ranking

        per_point = {"mean_return": [np.ravel(e["return"]) for e in evaluations],
                     "mean_length": [np.ravel(e["length"]) for e in evaluations]}
        if all("success" in e for e in evaluations):
            per_point["success_rate"] = [np.ravel(e["success"]) for e in evaluations]
        # Each point's mean (its episodes may differ in number across sessions): one column per point.
        means = {k: np.asarray([[np.mean(x)] for x in v], np.float64) for k, v in per_point.items()}
        return ranking(target).best_table(means)

    def score(e: dict[str, Any]) -> tuple[float, float]:
        return (float(np.mean(e["success"])) if "success" in e else 0.0, float(np.mean(e["return"])))

    scores = [score(e) for e in evaluations]
    return scores.index(max(scores))


class TrainingStopped(Exception):
    """:func:`train` stopped where the trainer handed back control (an evaluation point or a host iteration's end)
    because ``should_stop()`` said so."""


class _TargetMet(Exception):
    """Raised out of Brax's trainer at the evaluation point that met the learning target (``stop_at_target``):
    :func:`train` ends there, complete."""


def target_met(evaluation: dict[str, Any], target: Any) -> bool:
    """Whether one evaluation point's fresh episodes meet the task's learning ``target`` (None: never)."""
    if target is None:
        return False
    figure = {"success_rate": "success", "mean_return": "return", "mean_length": "length"}[target.metric]
    if figure not in evaluation:
        return False
    return bool(target.reached(float(np.mean(evaluation[figure]))))


class TrainerWatch:
    """Where the thread running :func:`train` is, for a watchdog that may have to end the process (see
    :class:`jaxrobo.training.driver.StopOnSignal`'s ``abandon``): ``in_trainer`` is True while Brax's trainer has
    control (compiling, or running a host iteration: it hands control back only when that ends), False while
    jaxrobo's own code runs (evaluating, keeping the run's files) or once the trainer returned. ``lock`` is held
    while the run's files are written and while ``in_trainer`` changes: a watchdog that takes it and finds
    ``in_trainer`` True may end the process with every kept file whole."""

    def __init__(self) -> None:
        import threading

        self.lock = threading.RLock()
        self.in_trainer = False


#: A host iteration that ends between evaluation points keeps the trainer's state (``on_chunk``) when a stop is
#: asked, the first of a session (after the trainer's compile), else at most every :data:`KEEP_SECONDS` and no
#: oftener than the time that keeping took times :data:`KEEP_COST_RATIO` (so keeping costs at most about
#: 1/KEEP_COST_RATIO of the training time).
KEEP_SECONDS = 10.0
KEEP_COST_RATIO = 20.0


def _epoch_metrics(chunks: list[dict[str, float]]) -> dict[str, float]:
    """An epoch's training metrics from those of its host iterations (equal numbers of training steps each):
    Brax's per-iteration means averaged, ``training/sps`` over the summed time, ``training/walltime`` the last."""
    if len(chunks) == 1:
        return dict(chunks[0])
    out = {k: float(np.mean([m[k] for m in chunks if k in m])) for k in chunks[-1]}
    if all(m.get("training/sps", 0) > 0 for m in chunks):
        out["training/sps"] = float(len(chunks) / sum(1.0 / m["training/sps"] for m in chunks))
    if "training/walltime" in chunks[-1]:
        out["training/walltime"] = chunks[-1]["training/walltime"]
    return out


def train(spec: DeepRunSpec, on_point: Callable[[Point], None] | None = None,
          should_stop: Callable[[], bool] | None = None, resume: Any = None,
          checkpoint_path: str = "checkpoint.npz", on_chunk: Callable[[Point], None] | None = None,
          watch: TrainerWatch | None = None) -> DeepResult:
    """Train with Brax's trainer on the env's Brax face; evaluate at each of its ``num_evals`` points.

    At each point the run's evaluation (:func:`evaluate`, fresh episodes of the jaxrobo env; Brax's own evaluator
    is not run) is made and ``on_point(point)`` (a :class:`Point`) is called, which is where a run keeps its work
    (:class:`jaxrobo.deep.output.LiveRun`: checkpoint, latest and best policy, CSV, TensorBoard). The trainer's
    epochs go through :func:`jaxrobo.interop.brax_compat.hook_epochs`, each as :attr:`EpochPlan.chunks` host
    iterations: their keys are :func:`chunk_keys`, their state is kept, and ``resume`` (a
    :class:`jaxrobo.deep.checkpoint.Saved` read from ``checkpoint_path``) puts a stopped run's state back at the
    first iteration, the trainer running only the iterations left. At the end of a host iteration between points,
    ``on_chunk(point)`` (``params`` None, ``chunks_done`` and ``partial_metrics`` set) keeps the trainer's state
    when a stop is asked, and now and then (:data:`KEEP_SECONDS`).

    Brax's trainer runs as one call with no way to pause it: ``should_stop()`` (e.g. a
    :class:`jaxrobo.training.driver.StopOnSignal`) is asked each time the trainer hands control back; after the
    state is kept (a point's evaluation and ``on_point``, or ``on_chunk``), or at once before any training,
    :class:`TrainingStopped` is raised out of the trainer. A stop asked at the last point ends nothing: the
    training is complete, the result is returned (its ``stopped_at_end`` says so). With ``stop_at_target`` the
    run ends, complete, at the first point (after its ``on_point``) whose evaluation meets the task's learning
    target: the result's ``target_met_at`` says which (env steps). ``watch`` (a :class:`TrainerWatch`) is kept
    up to date as control passes between the trainer and this code."""
    import jax

    from jaxrobo.deep.checkpoint import restore_states
    from jaxrobo.deep.config import check_spec
    from jaxrobo.interop import brax_env  # its import gives Brax 0.14's trainers the JAX calls they need
    from jaxrobo.interop.brax_compat import hook_epochs

    check_spec(spec)  # a Python caller's spec, checked as resolve checks the command line's values
    c = spec.config
    plan = epoch_plan(c)
    benv = brax_env.BraxEnv(spec.env)
    length = spec.episode_length
    watch = watch if watch is not None else TrainerWatch()
    done0 = resume.epochs_done if resume is not None else 0
    part0 = resume.chunks_done if resume is not None else 0
    going_on = done0 > 0 or part0 > 0
    evaluations: list[dict[str, Any]] = list(resume.evaluations) if going_on else []
    metrics_log: list[dict[str, float]] = list(resume.training_metrics) if going_on else []
    partial: list[dict[str, float]] = list(resume.partial_metrics) if going_on else []
    seconds0 = resume.train_seconds if going_on else 0.0
    steps0 = plan.env_steps(done0, part0) if going_on else 0
    timer = {"eval": 0.0, "start": time.perf_counter(), "evaluate": None}
    kept = {"at": time.perf_counter(), "cost": 0.0, "chunks": 0}
    key = jax.random.fold_in(jax.random.key(c.seed), 7)
    net = network_config(spec, int(benv.observation_size), int(benv.action_size))
    pending: dict[str, Any] = {}
    final: dict[str, Any] = {}

    def stop_here() -> None:
        if should_stop is not None and should_stop():
            raise TrainingStopped(f"stopped at {len(evaluations)} of {plan.points(plan.epochs)} evaluation points")

    def train_seconds(now: float) -> float:
        return seconds0 + now - timer["start"] - timer["eval"]

    target = getattr(spec.env, "learning_target", None) if c.stop_at_target else None

    def point(params: Any, epochs_done: int, chunks_done: int = 0) -> Point:
        seconds = evaluations[-1]["seconds"] if chunks_done == 0 else train_seconds(time.perf_counter())
        return Point(spec, net, plan, epochs_done, evaluations, metrics_log, hook.states, params, seconds, steps0,
                     seconds0, chunks_done, list(partial))

    def complete(params: Any) -> None:
        pending.clear()
        epochs_done = hook.epochs_done // plan.chunks
        if on_point is not None:
            with watch.lock:
                on_point(point(params, epochs_done))
            kept["at"] = time.perf_counter()
        if evaluations[-1]["env_steps"] > 0 and target_met(evaluations[-1], target):
            final["params"] = params
            raise _TargetMet()
        if epochs_done < plan.epochs:
            stop_here()
        elif should_stop is not None and should_stop():
            final["stopped_at_end"] = True

    def chunk_end() -> None:
        """A host iteration ended between evaluation points: keep the state if a stop is asked or it is time."""
        epochs_done, chunks_done = divmod(hook.epochs_done, plan.chunks)
        stopping = should_stop is not None and should_stop()
        now = time.perf_counter()
        due = kept["chunks"] == 0 or now - kept["at"] >= max(KEEP_SECONDS, KEEP_COST_RATIO * kept["cost"])
        if on_chunk is not None and (stopping or due):  # the session's first: after the compile, and timed
            with watch.lock:
                on_chunk(point(None, epochs_done, chunks_done))
            kept["at"] = time.perf_counter()
            kept["cost"], kept["chunks"] = kept["at"] - now, kept["chunks"] + 1
        if stopping:
            raise TrainingStopped(f"stopped after {plan.env_steps(epochs_done, chunks_done):,} env steps, between "
                                  f"evaluation points {len(evaluations)} and {len(evaluations) + 1} of "
                                  f"{plan.points(plan.epochs)}")

    def handing_back(fn: Callable) -> Callable:
        """``fn`` as a trainer callback: ``watch`` says jaxrobo's code has control until it returns normally."""
        def run(*args: Any) -> None:
            with watch.lock:
                watch.in_trainer = False
            fn(*args)
            with watch.lock:  # after the last iteration the trainer only returns: nothing left to abandon
                watch.in_trainer = hook.epochs_done < plan.epochs * plan.chunks

        return run

    def on_params(step: int, _make_policy: Callable | None, params: Any) -> None:  # (the net's own: the same)
        if step == 0:
            stop_here()  # nothing trained yet: nothing to keep
            if going_on or not plan.initial_point:
                return  # a resumed run's first callback (the parameters of where it stopped), or a SAC without one
        elif hook.epochs_done % plan.chunks:
            if c.agent != "ppo":
                chunk_end()  # (PPO hands its training metrics over next, in progress_fn, and ends there)
            return
        t0 = time.perf_counter()
        if timer["evaluate"] is None:
            timer["evaluate"] = evaluate(spec.env, benv, net, c.eval_episodes, length)
        # The host copy is evaluated: the trainer hands its first parameters and its trained ones with other
        # shardings, and the jitted evaluation would compile again for the second kind.
        host = jax.device_get(params)
        res = jax.device_get(timer["evaluate"](host, jax.random.fold_in(key, len(evaluations))))
        row = {k: np.asarray(v) for k, v in res.items()}
        row["env_steps"] = int(step)
        row["seconds"] = train_seconds(t0)
        evaluations.append(row)
        timer["eval"] += time.perf_counter() - t0
        if c.agent == "ppo" and step != 0:
            pending["params"] = host  # PPO hands its training metrics over next, in progress_fn
        else:
            complete(host)

    def on_progress(step: int, metrics: Mapping[str, Any]) -> None:
        if step == 0:
            stop_here()  # nothing trained yet: nothing to keep
            return
        partial.append({k: float(np.asarray(v)) for k, v in metrics.items() if np.size(v) == 1})
        if hook.epochs_done % plan.chunks == 0:
            metrics_log.append({"env_steps": int(step), **_epoch_metrics(partial)})
            partial.clear()
        if pending:
            complete(pending["params"])
        elif c.agent == "ppo":
            chunk_end()

    num_timesteps, num_evals = plan.trainer_budget(done0, part0) if going_on else plan.trainer_budget(0)
    common = dict(environment=benv, num_timesteps=num_timesteps, episode_length=length,
                  action_repeat=c.action_repeat, num_envs=c.num_envs, learning_rate=c.learning_rate,
                  discounting=c.discounting, seed=c.seed, batch_size=c.batch_size, num_evals=num_evals,
                  normalize_observations=c.normalize_observations, reward_scaling=c.reward_scaling,
                  max_devices_per_host=1, network_factory=_factory(spec), progress_fn=handing_back(on_progress),
                  wrap_env_fn=brax_env.wrap_for_training)
    restore = (lambda fresh: restore_states(checkpoint_path, resume, fresh)) if going_on else None
    first = done0 * plan.chunks + part0
    keys = functools.partial(chunk_keys, c, plan)
    # What Brax's epoch is traced from: the trainer's arguments below (the env, the config, the networks, the
    # budget of this call) and Brax's code (its version is in the key).
    epoch_parts = ("brax training_epoch", spec.env, c, net, num_timesteps, num_evals, length)
    compile_epoch = functools.partial(_compile_epoch, c.agent, epoch_parts)
    try:
        watch.in_trainer = True
        if c.agent == "ppo":
            from brax.training.agents.ppo import train as ppo

            with hook_epochs(ppo, keys, first, restore, compile_epoch=compile_epoch) as hook:
                _, params, _ = ppo.train(**common, entropy_cost=c.entropy_cost, unroll_length=c.unroll_length,
                                         num_minibatches=c.num_minibatches,
                                         num_updates_per_batch=c.num_updates_per_batch,
                                         clipping_epsilon=c.clipping_epsilon, gae_lambda=c.gae_lambda,
                                         max_grad_norm=c.max_grad_norm, policy_params_fn=handing_back(on_params),
                                         run_evals=False)
        else:
            from brax.training.agents.sac import train as sac

            with hook_epochs(sac, keys, first, restore, compile_epoch=compile_epoch) as hook:
                params = _train_sac(common, c, handing_back(lambda step, p: on_params(step, None, p)))
        hook.check()
        met_at = None
    except _TargetMet:
        params, met_at = final["params"], int(evaluations[-1]["env_steps"])
    finally:
        with watch.lock:
            watch.in_trainer = False
    seconds = time.perf_counter() - timer["start"]
    return DeepResult(spec, jax.device_get(params), net, evaluations, metrics_log, seconds, timer["eval"],
                      train_seconds=evaluations[-1]["seconds"], resumed_after_env_steps=steps0,
                      target_met_at=met_at, stopped_at_end=bool(final.get("stopped_at_end")))


def _compile_epoch(agent: str, parts: tuple, mapped: Callable, args: tuple, donate: tuple) -> Callable | None:
    """Brax's mapped training epoch compiled through a kept trace (:mod:`jaxrobo.speed.reuse`, program
    ``deep_epoch_<agent>``): a warm run traced it in every process (QuadcopterGotoTwist-v0's PPO epoch: 1.6 s of
    tracing and 0.4 s of lowering on an H200). None where the process does not reuse traces: the trainer then
    runs its own mapped epoch, as before. ``parts``: what the epoch is traced from (see :func:`train`)."""
    from jaxrobo.speed import reuse
    from jaxrobo.speed.plan import ExecutionPlan

    if not reuse.available() or args[-1].shape[0] != 1:
        return None  # (one device: the kept program is compiled for the devices it was traced on)
    return reuse.compile_reusing(ExecutionPlan(reuse_traces=True), f"deep_epoch_{agent}", mapped, args, parts,
                                 donate=donate)


def _train_sac(common: dict[str, Any], c: SACConfig, on_params: Callable[[int, Any], None]) -> Any:
    """``sac.train`` with the run's evaluation at each of its evaluation points.

    Brax's SAC takes no ``policy_params_fn``: it hands the parameters at each point to the
    ``acting.Evaluator`` it builds, then calls ``progress_fn(step, metrics)``. For the length of the call
    :func:`jaxrobo.interop.brax_compat.keep_evaluator_params` makes that evaluator one that keeps those parameters (and
    skips Brax's own evaluation rollout), and ``progress_fn`` runs the run's evaluation with them at that step;
    the trainer itself runs unchanged. The replay buffer's size is given explicitly (Brax's default is the
    call's ``num_timesteps``, which a resumed run's call makes smaller)."""
    from brax.training.agents.sac import train as sac

    from jaxrobo.interop.brax_compat import keep_evaluator_params

    progress = common["progress_fn"]
    with keep_evaluator_params() as hook:
        def on_progress(step: int, metrics: Mapping[str, Any]) -> None:
            progress(step, metrics)
            if hook.has_params:
                on_params(step, hook.pop())

        _, params, _ = sac.train(**{**common, "progress_fn": on_progress}, tau=c.tau,
                                 min_replay_size=c.min_replay_size,
                                 max_replay_size=c.max_replay_size or c.total_steps,
                                 grad_updates_per_step=c.grad_updates_per_step, num_eval_envs=1)
    hook.check()
    return params
