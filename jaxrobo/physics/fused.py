"""The fused training path: an execution-plan choice (:attr:`jaxrobo.speed.plan.ExecutionPlan.fused`) that keeps an
env's work together instead of moving the whole batch through memory at every stage of every step.

The plain path (``fused="off"``) runs a chunk as one ``lax.scan`` over steps of the whole batch: every step is
20-30 batch-wide kernels on a GPU (act, physics, discretise, table reads, update, records, resets), each reading
and writing part of every env's state, and a closed form with more than 8 physics substeps per control step (the
quadcopter's 30) runs them as a rolled loop, one round trip of the whole state through memory per substep.

``fused="xla"`` changes two things:

* **Substeps written out.** A closed-form backend (``Simulator.cheap_step``) unrolls all its physics substeps
  whatever their count (:func:`unroll_all_substeps`, read by :meth:`jaxrobo.physics.sim.Simulator.advance` while tracing
  under the plan), so XLA fuses across substeps instead of keeping a loop. On an H100 it still splits the
  written-out physics into several kernels, but the step ran 1.3-1.6x faster for the quadcopter (the plan's
  default for a closed form of many substeps without a kernel: :func:`jaxrobo.speed.plan.default_fused`; the rigid
  quadcopter's default is now its kernel, ``"pallas"``).
* **Steps inside blocks of envs** (``fused_block``). The chunk runs block after block of ``fused_block`` envs, each
  block doing all ``chunk_steps`` steps before the next starts (:meth:`jaxrobo.training.trainer.Trainer.run_chunk`): the
  loop over steps moves inside the loop over envs, so a block's carry can stay in cache across its steps. Envs with
  their own tables are independent, so the values are those of the plain path bit for bit; with a shared table they are
  not (each step's update mixes every env), so a shared table always runs unblocked. Measured slower on both an H100 and
  2 CPU cores (docs/benchmarks.md, "Fused path"): an option to measure, never a default.

What stays the same: the step itself (:meth:`jaxrobo.training.trainer.Trainer.step`), its random keys (each env's own),
its records, its resets: the fused path is that step rearranged, which is how the tests hold it to the plain
path as its oracle (same tables and records bit for bit on a CPU, whatever the blocks and the chunking). On a GPU
XLA may contract the written-out substeps' multiply-adds differently, so values can differ in the last bits
there, and a tabular run then takes another path (within the seed-to-seed spread in the runs measured).

``fused="pallas"`` (a choice :mod:`jaxrobo.speed.plan` adds) is read here too: a robot that offers a kernel for its
control step (:attr:`jaxrobo.task.robot.Robot.advance_kernel`, the rigid quadcopter's) has a vmapped step call it once
on the whole batch (:func:`physics_kernels`, read by :meth:`jaxrobo.physics.sim.Simulator.advance`); the rest of the
step stays XLA's. The cart-pole's whole-chunk kernel is its task's ``chunk_kernel`` (:mod:`envs.cartpole.kernel`), which
the trainer runs itself.

Public surface: :data:`CHOICES`, :func:`unroll_all_substeps`, :func:`physics_kernels`, :func:`task_kernels`,
:func:`choose`. The module imports nothing of jaxrobo's: the simulators and tasks read its flags and the plan its
choices, and the trainer runs
the blocks.
"""
from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator


#: The values of ``ExecutionPlan.fused``.
CHOICES = ("off", "xla")

_UNROLL_ALL: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxrobo_unroll_all_substeps", default=False)
_KERNELS: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxrobo_physics_kernels", default=False)
_TASK_KERNELS: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxrobo_task_kernels", default=False)


def unroll_all_substeps() -> bool:
    """Whether a closed-form simulator traced now writes out all its physics substeps (the innermost
    :func:`choose` block's choice; False outside any)."""
    return _UNROLL_ALL.get()


def physics_kernels() -> bool:
    """Whether a control step traced now runs through its robot's kernel where it has one (the innermost
    :func:`choose` block's choice is ``"pallas"``; False outside any)."""
    return _KERNELS.get()


def task_kernels() -> bool:
    """Whether a task step traced now runs as its task's whole-step kernel where it has one (the innermost
    :func:`choose` block's choice is ``"pallas"`` with ``task_kernel``; False outside any)."""
    return _TASK_KERNELS.get()


@contextlib.contextmanager
def choose(fused: str, task_kernel: bool = False) -> Iterator[None]:
    """Within this block (this thread or task), traces follow the fused choice ``fused`` (one of
    :data:`CHOICES`, or ``"pallas"``); with ``"pallas"`` and ``task_kernel``, a task with a kernel for its whole
    step runs that instead of the robot's control-step kernel."""
    token = _UNROLL_ALL.set(fused != "off")
    kernels = _KERNELS.set(fused == "pallas")
    tasks = _TASK_KERNELS.set(fused == "pallas" and task_kernel)
    try:
        yield
    finally:
        _TASK_KERNELS.reset(tasks)
        _KERNELS.reset(kernels)
        _UNROLL_ALL.reset(token)
