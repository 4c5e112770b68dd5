"""Training with Brax's trainers (:func:`train`, :class:`DeepResult`, :class:`TrainingStopped`) and the run's own
evaluation of the deterministic policy on fresh episodes of the jaxrobo env (:func:`evaluate`)."""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Mapping

import numpy as np

from jaxrobo.deep.config import DeepRunSpec, SACConfig
from jaxrobo.deep.policy import _factory, _networks, env_policy, network_config


# ---- evaluation ----------------------------------------------------------------------------------------------------
def evaluate(env: Any, benv: Any, make_policy: Callable, n_episodes: int, horizon: int) -> Callable:
    """A jitted ``(params, key) -> dict`` of ``n_episodes`` fresh episodes of the deterministic policy on the
    jaxrobo env (:func:`jaxrobo.task.rollout.rollout`): ``return``, ``length``, ``terminated`` and, for a task with an
    ``arrived`` flag, ``success``."""
    import jax

    from jaxrobo.task.rollout import outcomes, rollout

    # The step limit of training (the wrapper's episode_length) is the evaluation's too.
    env_params = benv.params.replace(max_episode_steps=horizon)

    def run(params, key):
        res = outcomes(rollout(env, env_policy(benv, make_policy, params), key, n_episodes, horizon, env_params))
        if "arrived" in res:
            res["success"] = res.pop("arrived")
        return res

    return jax.jit(run)


# ---- training ----------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class DeepResult:
    """What a deep run produced (host values)."""

    spec: DeepRunSpec
    params: Any
    net: dict[str, Any]
    #: One dict per evaluation: ``env_steps``, ``seconds`` (training wall time so far, compile included, the
    #: evaluations excluded) and the episodes' ``return``/``length``/``terminated`` (and ``success``) arrays.
    evaluations: list[dict[str, Any]]
    #: Brax's training metrics at each evaluation point after the first (losses, ``training/sps``, ...).
    training_metrics: list[dict[str, float]]
    seconds: float  # wall time of the trainer call, compile and evaluations included
    eval_seconds: float  # of which the evaluations

    @property
    def env_steps(self) -> int:
        return int(self.evaluations[-1]["env_steps"]) if self.evaluations else 0

    def summary(self) -> dict[str, Any]:
        c = self.spec.config
        last = self.evaluations[-1]
        train_seconds = self.seconds - self.eval_seconds
        out: dict[str, Any] = {
            "env_id": self.spec.env_id, "agent": c.agent, "preset": self.spec.preset,
            "num_envs": c.num_envs, "num_timesteps": c.num_timesteps, "env_steps": self.env_steps,
            "episode_length": self.spec.episode_length,
            "train_seconds": round(train_seconds, 3), "eval_seconds": round(self.eval_seconds, 3),
            "env_steps_per_second": round(self.env_steps / max(train_seconds, 1e-9), 1),
            "evaluations": len(self.evaluations), "eval_episodes": c.eval_episodes,
            "final_eval_mean_return": float(np.mean(last["return"])),
            "final_eval_mean_length": float(np.mean(last["length"])),
            "best_eval_mean_return": float(max(np.mean(e["return"]) for e in self.evaluations)),
        }
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
        return out


class TrainingStopped(Exception):
    """:func:`train` stopped at one of the trainer's evaluation points because ``should_stop()`` said so."""


def train(spec: DeepRunSpec, progress: Callable[[dict[str, Any]], None] | None = None,
          should_stop: Callable[[], bool] | None = None) -> DeepResult:
    """Train with Brax's trainer on the env's Brax face; evaluate at each of its ``num_evals`` points.

    ``progress(evaluation)`` is called with each evaluation's dict (host arrays). Brax's own evaluator is not
    run (``run_evals=False`` for PPO; SAC's ``num_eval_envs`` is kept minimal): the run's evaluation is
    :func:`evaluate` on fresh episodes of the jaxrobo env.

    Brax's trainer runs as one call with no way to pause it: ``should_stop()`` (e.g. a
    :class:`jaxrobo.training.driver.StopOnSignal`) is asked each time the trainer hands control back (its progress and
    parameter callbacks, at each evaluation point), and :class:`TrainingStopped` is raised out of the trainer
    there when it says so; nothing of the unfinished training is returned."""
    import jax

    from jaxrobo.interop import brax_env  # its import gives Brax 0.14's trainers the JAX calls they need

    c = spec.config
    benv = brax_env.BraxEnv(spec.env)
    length = spec.episode_length
    evaluations: list[dict[str, Any]] = []
    metrics_log: list[dict[str, float]] = []
    timer = {"eval": 0.0, "start": time.perf_counter(), "net": None, "evaluate": None}
    key = jax.random.fold_in(jax.random.key(c.seed), 7)
    net = network_config(spec, int(benv.observation_size), int(benv.action_size))

    def stop_here() -> None:
        if should_stop is not None and should_stop():
            raise TrainingStopped(f"stopped at {len(evaluations)} of {c.num_evals} evaluation points")

    def on_params(step: int, make_policy: Callable, params: Any) -> None:
        stop_here()
        t0 = time.perf_counter()
        if timer["evaluate"] is None:
            timer["evaluate"] = evaluate(spec.env, benv, make_policy, c.eval_episodes, length)
        res = jax.device_get(timer["evaluate"](params, jax.random.fold_in(key, len(evaluations))))
        row = {k: np.asarray(v) for k, v in res.items()}
        row["env_steps"] = int(step)
        row["seconds"] = t0 - timer["start"] - timer["eval"]
        evaluations.append(row)
        timer["eval"] += time.perf_counter() - t0
        if progress is not None:
            progress(row)

    def on_progress(step: int, metrics: Mapping[str, Any]) -> None:
        stop_here()
        if metrics:
            metrics_log.append({"env_steps": int(step), **{k: float(np.asarray(v)) for k, v in metrics.items()
                                                            if np.size(v) == 1}})

    common = dict(environment=benv, num_timesteps=c.num_timesteps, episode_length=length,
                  action_repeat=c.action_repeat, num_envs=c.num_envs, learning_rate=c.learning_rate,
                  discounting=c.discounting, seed=c.seed, batch_size=c.batch_size, num_evals=c.num_evals,
                  normalize_observations=c.normalize_observations, reward_scaling=c.reward_scaling,
                  max_devices_per_host=1, network_factory=_factory(spec), progress_fn=on_progress,
                  wrap_env_fn=brax_env.wrap_for_training)
    if c.agent == "ppo":
        from brax.training.agents.ppo import train as ppo

        _, params, _ = ppo.train(**common, entropy_cost=c.entropy_cost, unroll_length=c.unroll_length,
                                 num_minibatches=c.num_minibatches, num_updates_per_batch=c.num_updates_per_batch,
                                 clipping_epsilon=c.clipping_epsilon, gae_lambda=c.gae_lambda,
                                 max_grad_norm=c.max_grad_norm, policy_params_fn=on_params, run_evals=False)
    else:
        params = _train_sac(common, c, lambda step, p: on_params(step, _networks(net)[1], p))
    seconds = time.perf_counter() - timer["start"]
    return DeepResult(spec, jax.device_get(params), net, evaluations, metrics_log, seconds, timer["eval"])


def _train_sac(common: dict[str, Any], c: SACConfig, on_params: Callable[[int, Any], None]) -> Any:
    """``sac.train`` with the run's evaluation at each of its evaluation points.

    Brax's SAC takes no ``policy_params_fn``: it hands the parameters at each point to the
    ``acting.Evaluator`` it builds, then calls ``progress_fn(step, metrics)``. For the length of the call
    :func:`jaxrobo.interop.brax_compat.keep_evaluator_params` makes that evaluator one that keeps those parameters (and
    skips Brax's own evaluation rollout), and ``progress_fn`` runs the run's evaluation with them at that step;
    the trainer itself runs unchanged."""
    from brax.training.agents.sac import train as sac

    from jaxrobo.interop.brax_compat import keep_evaluator_params

    progress = common["progress_fn"]
    with keep_evaluator_params() as hook:
        def on_progress(step: int, metrics: Mapping[str, Any]) -> None:
            progress(step, metrics)
            if hook.has_params:
                on_params(step, hook.pop())

        _, params, _ = sac.train(**{**common, "progress_fn": on_progress}, tau=c.tau,
                                 min_replay_size=c.min_replay_size, max_replay_size=c.max_replay_size,
                                 grad_updates_per_step=c.grad_updates_per_step, num_eval_envs=1)
    hook.check()
    return params
