"""Callbacks of a training run (:func:`jaxrobo.training.train.train`), shaped like Stable-Baselines3's
``BaseCallback``: a run calls each hook at its point, and ``on_chunk`` returning False stops the run at that chunk
boundary (SB3's ``_on_step``), its carry checkpointed as a signal's stop is.

The command line, the sweeps' and notebooks' runs and the Python API hand the same :func:`train` the same
callbacks: :class:`ProgressBar` (tqdm), :class:`LiveScalars` (TensorBoard scalars as the run goes),
:class:`EvaluationLines` (the final evaluation's progress on stderr) and any of a user's own.

Public surface: :class:`Callback`, :class:`CallbackList`, :func:`as_callbacks`, :class:`ProgressBar`,
:class:`LiveScalars`, :class:`EvaluationLines`.
"""
from __future__ import annotations

import inspect
import os
import sys
from typing import Any, Callable, Iterable

from jaxrobo.training.driver import EvalProgress, Progress


class Callback:
    """A training run's hooks; override the ones you need (each defaults to doing nothing)."""

    def on_training_start(self, trainer: Any, initial: Any) -> None:
        """Before the first compile: ``trainer`` (:class:`~jaxrobo.training.trainer.Trainer`) and the carry the run
        starts from (None: a fresh one; a sweep group's: its rows' carry)."""

    def on_chunk(self, progress: Progress) -> bool | None:
        """After each chunk (:class:`~jaxrobo.training.driver.Progress`); False stops the run at this boundary."""
        return None

    def on_evaluation_start(self, line: str) -> None:
        """The greedy evaluation after the last chunk starts (``line`` says what it flies)."""

    def on_evaluation(self, progress: EvalProgress) -> None:
        """After each segment of the greedy evaluation (:class:`~jaxrobo.training.driver.EvalProgress`)."""

    def on_training_end(self, result: Any) -> None:
        """The run's :class:`~jaxrobo.training.summary.TrainResult` (complete or stopped); a sweep group's
        :class:`~jaxrobo.training.driver.PopulationResult`."""


class CallbackList(Callback):
    """Several callbacks as one, called in order; ``stop_requested`` once any ``on_chunk`` returned False."""

    def __init__(self, callbacks: Iterable[Callback]) -> None:
        self.callbacks = list(callbacks)
        self.stop_requested = False

    def on_training_start(self, trainer: Any, initial: Any) -> None:
        for c in self.callbacks:
            c.on_training_start(trainer, initial)

    def on_chunk(self, progress: Progress) -> bool:
        go_on = [c.on_chunk(progress) is not False for c in self.callbacks]  # every callback hears every chunk
        self.stop_requested = self.stop_requested or not all(go_on)
        return not self.stop_requested

    def on_evaluation_start(self, line: str) -> None:
        for c in self.callbacks:
            c.on_evaluation_start(line)

    def on_evaluation(self, progress: EvalProgress) -> None:
        for c in self.callbacks:
            c.on_evaluation(progress)

    def on_training_end(self, result: Any) -> None:
        for c in self.callbacks:
            c.on_training_end(result)


class _ProgressFunction(Callback):
    """A plain function of each chunk's :class:`Progress` (or, with three parameters, of ``(done, total,
    last_return)``), as ``train``'s ``progress`` argument took before callbacks."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        try:
            params = [p for p in inspect.signature(fn).parameters.values()
                      if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty]
        except (TypeError, ValueError):
            params = []
        self.fn = (lambda p: fn(p.done, p.total, p.last_return)) if len(params) == 3 else fn

    def on_chunk(self, progress: Progress) -> bool | None:
        self.fn(progress)
        return None


def as_callbacks(callbacks: Callback | Callable[..., Any] | Iterable[Any] | None) -> CallbackList:
    """``callbacks`` (None, a :class:`Callback`, a progress function, or a sequence of them) as one list;
    TypeError naming what is not one."""
    if callbacks is None:
        return CallbackList([])
    try:
        items = [callbacks] if isinstance(callbacks, Callback) or callable(callbacks) else list(callbacks)
    except TypeError:  # not iterable: list()'s own message names no argument
        raise TypeError(f"callbacks: {callbacks!r} is neither a jaxrobo.training.callbacks.Callback, a function nor a "
                        "sequence of them") from None
    out = []
    for c in items:
        if isinstance(c, Callback):
            out.append(c)
        elif callable(c):
            out.append(_ProgressFunction(c))
        else:
            raise TypeError(f"callbacks: {c!r} is neither a jaxrobo.training.callbacks.Callback nor a function")
    return CallbackList(out)


class ProgressBar(Callback):
    """A tqdm bar over the run's budget (episodes per env, steps per env, or the run's episodes), from where a
    resumed carry is, with the latest return and the useful share of env slots; closed when the evaluation starts."""

    def __init__(self) -> None:
        self.bar = None

    def on_training_start(self, trainer: Any, initial: Any) -> None:
        import jax
        from tqdm.auto import tqdm

        total, unit = trainer.budget_total
        done0 = 0 if initial is None else int(jax.device_get(trainer.progress(initial))[0])
        desc = {"episodes": "training (episodes per env)", "steps": "training (steps per env)",
                "run_episodes": "training (episodes of the run)"}[trainer.budget]
        self.bar = tqdm(total=total, initial=min(done0, total), unit="ep" if unit == "episodes" else "step",
                        desc=desc, dynamic_ncols=True)

    def on_chunk(self, progress: Progress) -> None:
        if self.bar is not None:
            self.bar.update(progress.done - self.bar.n)
            self.bar.set_postfix(last_return=f"{progress.last_return:.1f}", useful=f"{progress.useful_share:.0%}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def on_evaluation_start(self, line: str) -> None:
        self.close()

    def on_training_end(self, result: Any) -> None:
        self.close()


class EvaluationLines(Callback):
    """The greedy evaluation on stderr: the line that starts it and, with ``segments``, one per segment (steps
    done, episodes still running, an ETA that is an upper bound: the flight ends with its last episode)."""

    def __init__(self, segments: bool = True) -> None:
        self.segments = segments

    def on_evaluation_start(self, line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    def on_evaluation(self, p: EvalProgress) -> None:
        if not self.segments:
            return
        eta = "done" if p.running == 0 else f"ETA ≤ {p.eta:.0f} s"
        print(f"  evaluation ({p.what}): step {p.step:,}/{p.horizon:,}, {p.running:,} of {p.episodes:,} episodes "
              f"running, {p.seconds:.0f} s (compiled in {p.compile_seconds:.0f} s), {eta}", file=sys.stderr,
              flush=True)


class LiveScalars(Callback):
    """TensorBoard scalars written as a run goes (:class:`jaxrobo.io.events.ScalarWriter`, flushed after every
    chunk), against env steps: ``progress/useful_share``, ``progress/done`` (in the budget's unit),
    ``train/last_return`` (the mean over envs of each env's latest recorded episode, the progress bar's
    ``last_return``) and ``progress/steps_per_second``. Nothing is written (one line says why) if the folder cannot
    be made."""

    def __init__(self, run_dir: str) -> None:
        self.writer = None
        try:
            from jaxrobo.io.events import ScalarWriter

            self.writer = ScalarWriter(os.path.join(run_dir, "tensorboard"))
        except (ImportError, OSError) as err:
            print(f"jaxrobo: no live TensorBoard scalars ({err})", file=sys.stderr)

    def on_chunk(self, p: Progress) -> None:
        if self.writer is None:
            return
        step = int(p.useful_steps) if p.useful_steps == p.useful_steps else p.chunks_done
        self.writer.add_scalar("progress/done", p.done, step)
        self.writer.add_scalar("progress/useful_share", p.useful_share, step)
        self.writer.add_scalar("train/last_return", p.last_return, step)
        if p.seconds > 0:
            self.writer.add_scalar("progress/steps_per_second", p.steps_per_second, step)  # this process's
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def on_training_end(self, result: Any) -> None:
        self.close()
