"""TensorBoard scalars written synchronously, without tensorboardX's writer thread or its optional PyTorch import.

``tensorboardX.SummaryWriter`` hands each event to a worker thread through a ``multiprocessing.Queue`` and joins
it on ``close()``, and ``import tensorboardX`` imports PyTorch when it is installed (for its tensor type): on a
machine with PyTorch that was seconds of a run's start and end, for a few hundred scalars. :class:`ScalarWriter`
writes the same event files (tensorboardX's protobuf messages and record framing, :class:`tensorboardX.RecordWriter`)
in the caller's thread; :func:`tensorboardx` imports tensorboardX with PyTorch hidden from it (its writer then
takes numpy arrays, which is all jaxrobo hands it). TensorBoard, :func:`jaxrobo.io.results.read_scalars` and
tensorboardX's own readers read the files alike.
"""
from __future__ import annotations

import contextlib
import importlib.abc
import os
import socket
import sys
import time
from types import ModuleType
from typing import Any, Iterator


class _Hidden(importlib.abc.MetaPathFinder):
    """A finder that says ``module`` (and its submodules) cannot be imported: put first on ``sys.meta_path``."""

    def __init__(self, module: str) -> None:
        self.module = module

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> None:
        if fullname == self.module or fullname.startswith(self.module + "."):
            raise ImportError(f"{self.module} is hidden while tensorboardX is imported", name=fullname)
        return None


@contextlib.contextmanager
def _without(module: str) -> Iterator[None]:
    """``import module`` raises ImportError inside the block, unless it was imported before; afterwards it
    imports as usual."""
    if module in sys.modules:
        yield
        return
    finder = _Hidden(module)
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)


def tensorboardx() -> ModuleType:
    """``tensorboardX``, imported without PyTorch (ImportError where tensorboardX is missing)."""
    if "tensorboardX" in sys.modules:
        return sys.modules["tensorboardX"]
    with _without("torch"):
        import tensorboardX
    return tensorboardX


class ScalarWriter:
    """Scalars into a new event file of ``logdir`` (``events.out.tfevents.<time>.<host>[suffix]``), each
    :meth:`add_scalar` written at once; :meth:`flush` pushes them to the file, :meth:`close` ends it."""

    def __init__(self, logdir: str, filename_suffix: str = "") -> None:
        tbx = tensorboardx()
        from tensorboardX.proto import event_pb2, summary_pb2

        self._event, self._summary = event_pb2.Event, summary_pb2.Summary
        os.makedirs(logdir, exist_ok=True)
        name = f"events.out.tfevents.{time.time():010.0f}.{socket.gethostname()}{filename_suffix}"
        self.path = os.path.join(logdir, name)
        self._writer = tbx.RecordWriter(self.path)
        self._write(self._event(wall_time=time.time(), file_version="brain.Event:2"))

    def _write(self, event) -> None:
        self._writer.write(event.SerializeToString())

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        summary = self._summary(value=[self._summary.Value(tag=tag, simple_value=float(value))])
        self._write(self._event(wall_time=time.time(), step=int(step), summary=summary))

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> "ScalarWriter":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()
