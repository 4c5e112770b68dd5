"""Vectorised tabular training: the seed's episodes × steps loop, for ``n_envs`` environments at once.

:func:`train` is the public entry: it builds a :class:`~jaxrobo.training.trainer.Trainer` for an env and a
:class:`~jaxrobo.training.trainer.TrainConfig`, runs it with the host driver (:func:`jaxrobo.training.driver.run_training`: compile
one chunk, run chunk after chunk, evaluate at the end) under the run's execution plan, and returns a
:class:`~jaxrobo.training.summary.TrainResult`. A run starts from a fresh carry or a saved one
(:func:`~jaxrobo.training.checkpoint.save_checkpoint` / :func:`~jaxrobo.training.checkpoint.load_checkpoint`, what
``jaxrobo train --resume`` uses), hands the carry to a checkpoint callback now and then, and stops at a chunk
boundary when asked.

Where the pieces live: the config, the carry and the jitted step in :mod:`jaxrobo.training.trainer`; the host loop in
:mod:`jaxrobo.training.driver`; the result and its summary in :mod:`jaxrobo.training.summary`; checkpoints in
:mod:`jaxrobo.training.checkpoint`. Their public names are re-exported here, so ``from jaxrobo.training.train import Trainer,
TrainConfig, TrainResult, train`` keeps working.

Public surface: :func:`train` and the re-exports below.
"""
from __future__ import annotations

from typing import Any, Callable

from jaxrobo.tabular.learner import AgentParams
from jaxrobo.training.checkpoint import (CHECKPOINT_FORMAT, CheckpointError, carry_fingerprint, carry_template,
                                fingerprint_mismatch, load_checkpoint, read_fingerprint, save_checkpoint)
from jaxrobo.training.driver import CheckpointFn, ProgressFn, compiled_chunk, run_training
from jaxrobo.task.env import Env
from jaxrobo.speed.plan import ExecutionPlan
from jaxrobo.training.summary import TrainResult
from jaxrobo.training.trainer import Runner, TrainConfig, Trainer, make_discretiser_for, progress_stats

__all__ = ["train", "TrainConfig", "Runner", "Trainer", "TrainResult", "make_discretiser_for", "progress_stats",
           "compiled_chunk", "ProgressFn", "CheckpointFn", "CHECKPOINT_FORMAT", "CheckpointError", "carry_template",
           "carry_fingerprint", "fingerprint_mismatch", "save_checkpoint", "read_fingerprint", "load_checkpoint"]


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
    first chunk boundary ``checkpoint_seconds`` after the last one (neither: none on the way), once more after the
    last chunk (before the evaluation, so a late failure never loses the finished carry), and when
    ``should_stop()`` says to stop: that is asked before each chunk, so a stop request finishes the
    current chunk, saves it through ``checkpoint`` and returns a result with ``complete=False`` (episodes so
    far, no evaluation). The library installs no signal handlers; the CLI's ``should_stop`` is a
    :class:`jaxrobo.training.driver.StopOnSignal`. Evaluation runs only after the last chunk.

    ``plan``: how the run is executed (default: :meth:`jaxrobo.speed.plan.ExecutionPlan.for_run` of this env and
    config); everything the run traces, training chunks and evaluation, is traced under it."""
    trainer = Trainer(env, config, plan=plan)
    with trainer.plan.tracing():
        return run_training(trainer, agent_params, env_params, progress, initial=initial, start_chunk=start_chunk,
                            checkpoint=checkpoint, checkpoint_every=checkpoint_every,
                            checkpoint_seconds=checkpoint_seconds, should_stop=should_stop)
