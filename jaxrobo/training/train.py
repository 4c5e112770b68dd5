"""The one training entry: :func:`train`, which the command line, the sweeps, notebooks and the Python API all call.

It builds a :class:`~jaxrobo.training.trainer.Trainer` for an env and a :class:`~jaxrobo.training.trainer.TrainConfig`
and runs it with the host driver (:func:`jaxrobo.training.driver.run_training`: compile, run chunk after chunk
until the budget or the task's learning target, evaluate) under the run's execution plan, telling its callbacks
(:mod:`jaxrobo.training.callbacks`, Stable-Baselines3's shape) as it goes, and returns a
:class:`~jaxrobo.training.summary.TrainResult`. Given a :class:`~jaxrobo.training.driver.Population` (a sweep's
group: rows of runs vmapped into one program, :mod:`jaxrobo.training.sweep`), it runs the rows through the same
host loop, hooks and callbacks (:func:`jaxrobo.training.driver.run_population`) and returns a
:class:`~jaxrobo.training.driver.PopulationResult`.

Where the pieces live: the config, the carry and the jitted step in :mod:`jaxrobo.training.trainer`; the host loop
in :mod:`jaxrobo.training.driver`; the result and its summary in :mod:`jaxrobo.training.summary`; checkpoints in
:mod:`jaxrobo.training.checkpoint`.
"""
from __future__ import annotations

from typing import Any, Callable, Iterable

from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.tabular.learner import AgentParams
from jaxrobo.task.env import Env
from jaxrobo.training.callbacks import Callback, as_callbacks
from jaxrobo.training.driver import CheckpointFn, Population, PopulationResult, run_population, run_training
from jaxrobo.training.run import check_train_arguments
from jaxrobo.training.summary import TrainResult
from jaxrobo.training.trainer import Runner, TrainConfig, Trainer

__all__ = ["train"]


def train(env: Env, config: TrainConfig, agent_params: AgentParams | None = None, env_params: Any = None,
          callbacks: Callback | Callable[..., Any] | Iterable[Any] | None = None, *, initial: Runner | None = None,
          start_chunk: int = 0, checkpoint: CheckpointFn | None = None, checkpoint_every: int = 0,
          checkpoint_seconds: float | None = None, should_stop: Callable[[], bool] | None = None,
          plan: ExecutionPlan | None = None, trainer: Trainer | None = None,
          population: Population | None = None) -> TrainResult | PopulationResult:
    """Run a whole training: until the budget ends or the task's learning target holds (``stop_at_target``),
    then a greedy evaluation.

    ``callbacks``: :class:`~jaxrobo.training.callbacks.Callback` objects (or a plain function of each chunk's
    :class:`~jaxrobo.training.driver.Progress`, or of ``(done, total, last_return)``), told of the start, every
    chunk, the evaluation and the end; an ``on_chunk`` that returns False stops the run at that chunk boundary.

    The host loop runs chunk after chunk from ``initial`` (a carry after ``start_chunk`` chunks, e.g. from
    :func:`~jaxrobo.training.checkpoint.load_checkpoint`; default: a fresh ``Trainer.init``), so a resumed run is
    the uninterrupted one bit for bit: training is deterministic and does not depend on where the chunks are cut.
    ``initial`` is donated to the first chunk (its buffers are reused).

    ``checkpoint(runner, chunks_done)`` is called with the carry every ``checkpoint_every`` chunks and/or at the
    first chunk boundary ``checkpoint_seconds`` after the last one (neither: none on the way), once more after the
    last chunk (before the evaluation, so a late failure never loses the finished carry; one that saves in a
    thread, :class:`~jaxrobo.training.checkpoint.SaveInThread`, copies the carry once the evaluation is read back,
    whose reads from the device would otherwise queue behind that copy), and when the run is asked
    to stop (``should_stop()`` before each chunk, or a callback): the current chunk finishes, is saved, and the
    result has ``complete=False`` (episodes so far, no evaluation). The library installs no signal handlers; the
    CLI's ``should_stop`` is a :class:`jaxrobo.training.driver.StopOnSignal`.

    ``plan``: how the run is executed (default: :meth:`jaxrobo.speed.plan.ExecutionPlan.for_run` of this env and
    config); everything the run traces, training chunks and evaluation, is traced under it.

    ``trainer``: the :class:`~jaxrobo.training.trainer.Trainer` of this ``env`` and ``config`` that the caller
    built already (the command line builds one to check the budget and the memory and to trace the checkpoint's
    template): the run uses it, so what that trainer traced (its ``init``, under its plan) is not traced again.

    ``population``: train its rows as one program instead of one run (:func:`jaxrobo.training.driver.run_population`;
    ``agent_params`` / ``env_params`` hold the rows' parameters stacked, ``initial`` is the rows' carry): the same
    hooks, stop and checkpoints, except that the carry is not saved after the last chunk (the rows' measures are
    what a finished population keeps), there is no learning-target stop and no evaluation callbacks (the rows'
    greedy evaluation is part of the population's ``finish``); a :class:`~jaxrobo.training.driver.PopulationResult`."""
    hooks = as_callbacks(callbacks)
    # The command line's values were checked by run.resolve; a Python caller's get the same checks here, before the
    # trainer is built (a zero n_envs failed inside the execution plan, a NaN alpha trained NaN tables).
    check_train_arguments(env, config, agent_params, env_params, population=population is not None,
                          start_chunk=start_chunk, checkpoint_every=checkpoint_every,
                          checkpoint_seconds=checkpoint_seconds)
    if trainer is None:
        trainer = Trainer(env, config, plan=plan)
    elif trainer.env is not env or trainer.config != config or (plan is not None and plan != trainer.plan):
        raise ValueError("train(trainer=...): the trainer must be built for this env and config (and plan)")
    hooks.on_training_start(trainer, initial)

    def stop() -> bool:
        # should_stop first, always: under jax.distributed it may be a collective (driver.agreed_stop) that
        # every process calls at the same point, whatever this process's callbacks said.
        asked = should_stop is not None and should_stop()
        return hooks.stop_requested or asked

    with trainer.plan.tracing():
        if population is None:
            result = run_training(trainer, agent_params, env_params, hooks.on_chunk, initial=initial,
                                  start_chunk=start_chunk, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                                  checkpoint_seconds=checkpoint_seconds, should_stop=stop,
                                  announce=hooks.on_evaluation_start, eval_progress=hooks.on_evaluation)
        else:
            result = run_population(trainer, population, agent_params, env_params, hooks.on_chunk, initial=initial,
                                    start_chunk=start_chunk, checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                                    checkpoint_seconds=checkpoint_seconds, should_stop=stop)
    hooks.on_training_end(result)
    return result
