"""The tests' one way to stop a run at a checkpoint: a save function patched to raise a signal in this process right
after it has saved, where a Ctrl-C or a scheduler's SIGTERM would arrive between two chunks (or two sweep groups).
The run's own handler only takes note; the run then stops at its next boundary with the signal's exit status.

Imported by the test files beside it and by their child scripts (``sys.path`` given this folder)."""
from __future__ import annotations

import contextlib
import signal
from typing import Any, Callable, Iterator


def after_chunk(n: int) -> Callable[..., bool]:
    """For :func:`jaxrobo.training.checkpoint.save_checkpoint` ``(path, runner, chunks_done, ...)``: the save of the
    carry after ``n`` chunks."""
    return lambda path, runner, chunks_done, *args, **kwargs: chunks_done == n


def after_groups(n: int) -> Callable[..., bool]:
    """For :func:`jaxrobo.training.sweep.state.save_checkpoint` ``(state_dir, fingerprint, plan, finished)``: the
    save once ``n`` groups have finished."""
    return lambda state_dir, fingerprint, plan, finished, *args, **kwargs: len(finished) == n


@contextlib.contextmanager
def signal_after_save(module: Any, signum: int, when: Callable[..., bool] | None = None) -> Iterator[None]:
    """``module.save_checkpoint`` raising ``signum`` after each save for which ``when(*args, **kwargs)`` holds
    (``None``: after the first save only), the real one back when the block ends."""
    real = module.save_checkpoint
    calls = [0]

    def save_then_signal(*args: Any, **kwargs: Any) -> Any:
        saved = real(*args, **kwargs)
        calls[0] += 1
        if (calls[0] == 1) if when is None else when(*args, **kwargs):
            signal.raise_signal(signum)
        return saved

    module.save_checkpoint = save_then_signal
    try:
        yield
    finally:
        module.save_checkpoint = real
