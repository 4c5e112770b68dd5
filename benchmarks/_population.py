"""Independent runs of one preset trained side by side, for the learning benchmarks (``goto_learning.py``,
``arm_learning.py``, ``learning_targets.py``).

Each run is the run ``jaxrobo train --env ID --seed S`` would train (its own key, ``jax.random.key(S)``); the runs'
``trainer.init`` and chunk are vmapped over the seeds, the chunk compiled under the trainer's plan and looped by
the host driver as ``jaxrobo train``'s (:func:`jaxrobo.training.driver.compile_under`,
:func:`~jaxrobo.training.driver.run_chunks`), so that what a benchmark reports of a seed is what that command
would train.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp

from jaxrobo.training import driver
from jaxrobo.training.trainer import Trainer


@dataclasses.dataclass
class Population:
    """What :func:`train_population` ends with: the ``trainer`` (one run's), the ``seeds``, the vmapped carry
    ``runner`` (every leaf with a leading ``[runs]`` axis), the driver's ``loop`` (:class:`ChunkRun`: its
    ``chunks_done``) and the ``seconds`` of init, compile and training, the carry waited for."""

    trainer: Trainer
    seeds: list[int]
    runner: Any
    loop: driver.ChunkRun
    seconds: float


def compiled_population(spec: Any, seeds: list[int], plan: Any = None) -> tuple[Trainer, Any, Callable[[Any], Any]]:
    """One run of ``spec`` (a resolved preset: :func:`jaxrobo.training.run.resolve`) per seed in ``seeds``, ready
    to train as one vmapped computation: ``(trainer, runner, chunk)``, the fresh vmapped carry and its compiled
    chunk, ``chunk(runner) -> runner`` (the carry donated). ``plan``: the
    :class:`~jaxrobo.speed.plan.ExecutionPlan` to train under (None: the trainer's default for the run, as
    ``jaxrobo train`` builds it)."""
    trainer = Trainer(spec.env, spec.config, plan=plan)
    keys = jnp.stack([jax.random.key(s) for s in seeds])
    ap_, ep = spec.agent_params, spec.env.default_params
    runner = jax.jit(jax.vmap(trainer.init, in_axes=(0, None, None)))(keys, ap_, ep)
    plan = trainer.plan
    chunk = driver.compile_under(plan, jax.jit(jax.vmap(trainer.run_chunk, in_axes=(0, None, None)),
                                               donate_argnums=0, compiler_options=plan.xla_options), runner, ap_, ep)
    return trainer, runner, lambda r: chunk(r, ap_, ep)


def train_population(spec: Any, seeds: list[int], plan: Any = None) -> Population:
    """Train one run of ``spec`` per seed in ``seeds`` as one vmapped computation (:func:`compiled_population`),
    to the end of its budget, looped by the host driver as ``jaxrobo train`` loops its chunks; with ``snapshots``
    each run's carry then holds the table ``jaxrobo train`` keeps (:meth:`Trainer.final_table`, from its seed's
    key)."""
    seeds = list(seeds)
    t0 = time.perf_counter()
    trainer, runner, chunk = compiled_population(spec, seeds, plan)
    total, unit = trainer.budget_total
    loop = driver.run_chunks(chunk, runner, trainer.max_chunks(),
                             read=driver.compiled_progress(runner), total=total, unit=unit)
    carry = loop.carry
    if carry.snapshots is not None:  # each run keeps the table `jaxrobo train` would keep (Trainer.final_table)
        keys = jnp.stack([jax.random.key(s) for s in seeds])
        final = jax.jit(jax.vmap(trainer.final_table, in_axes=(0, 0, None)))
        carry = final(carry, keys, spec.env.default_params)[0]
    jax.block_until_ready(carry)
    return Population(trainer, seeds, carry, loop, time.perf_counter() - t0)
