"""Parameter sweeps as one vmapped, jitted computation: ``jaxrobo sweep``.

The seed's advice for tuning ("try several times with different parameters") becomes one command: a grid or a
random sample over learner parameters (alpha, gamma, epsilon, epsilon_discount, epsilon_min) and traced env
parameters (pos_step, limits, goals, ...), times seeds. Every (configuration, seed) row runs the whole training
loop of :class:`jaxrobo.training.trainer.Trainer` with its own ``n_envs`` environments and tables; the rows become a
leading axis of the parameter pytrees, and ``Trainer.init`` / ``Trainer.run_chunk`` are vmapped over it, so
the whole sweep is one compiled program (split over all devices when there are several, see
:mod:`jaxrobo.speed.sharding`). Settings that change array shapes or code (``number_splits``, ``agent``,
``running_step``, ``control_type``, ...) cannot be vmapped: the sweep groups the rows by them and compiles one
program per distinct combination.

Row ``(config c, seed s)`` uses ``jax.random.key(s)``, exactly like ``jaxrobo train --seed s``, so every
configuration sees the same random streams (the seed's "exact same conditions") and any row can be reproduced
with a single ``jaxrobo train`` run.

    jaxrobo sweep --env CartPoleStayUp-v0 --agent qlearn --grid alpha=0.1,0.3,0.5 --grid gamma=0.9,0.99 \\
        --seeds 4 --n-envs 8 --out runs/sweep
    jaxrobo sweep --random 64 --range alpha=0.05:0.9 --range epsilon_discount=0.99:0.9999 --seeds 2

Nothing is lost: ``--out`` is checked before anything compiles (an existing file, a non-empty directory without
``--overwrite``, a parent that cannot be written are refused, exit status 2). While the sweep runs, ``--out`` holds its
state: the settings and code versions (``sweep_state.json``), the metrics of every finished group (``checkpoint.npz``,
rewritten atomically after each group) and the carry of the group in progress (``group_<g>.npz``, every 5 minutes at a
chunk boundary and when stopped). Ctrl-C or SIGTERM finishes the chunk in flight, saves that carry and exits with 130 /
143; ``jaxrobo sweep --resume DIR`` reads the saved settings back, skips the finished groups, goes on inside the saved
group from its last chunk and writes the same ``sweep.csv`` and ``summary.json`` as an uninterrupted sweep (timings
aside). The results are written into a hidden sibling directory and replace the state in one rename, so a directory with
a ``sweep.csv`` is always a whole sweep.

One concern per module:

* :mod:`jaxrobo.training.sweep.planning`: the swept keys and their points (grid or random sample), checked and grouped
  by the values that change shapes or code, every group's run resolved (:func:`plan_sweep`), before anything compiles;
* :mod:`jaxrobo.training.sweep.running`: one compiled program per group (:class:`GroupRunner`: the group's rows as a
  :class:`~jaxrobo.training.driver.Population` trained by :func:`jaxrobo.training.train.train`, with the callbacks
  given to :func:`run_plan`), the groups run one after the other (:func:`run_plan`, :func:`run_sweep`) into a
  :class:`SweepResult`;
* :mod:`jaxrobo.training.sweep.state`: the saved progress (``sweep_state.json``, ``checkpoint.npz``) that ``--resume``
  reads back;
* :mod:`jaxrobo.training.sweep.output`: ``sweep.csv`` and the heatmaps;
* :mod:`jaxrobo.training.sweep.cli`: the flags of ``jaxrobo sweep``, ``--resume``, and the run from flags to results.

Public surface (all importable from ``jaxrobo.training.sweep``): :data:`METRICS`, :data:`NOT_SWEPT`, :data:`KeyKind`,
:func:`classify`, :func:`parse_grid`, :func:`parse_ranges`, :func:`grid_points`, :func:`random_points`,
:func:`plan_groups`, :class:`PlannedGroup`, :class:`SweepPlan`, :func:`plan_sweep`, :class:`SweepResult`,
:class:`GroupRunner`, :func:`run_sweep`, :func:`run_plan`, :class:`SweepInterrupted`, :data:`STATE_FILE`,
:data:`STATE_FORMAT`, :func:`code_version`, :func:`read_state`, :func:`open_state`, :func:`save_checkpoint`,
:func:`load_checkpoint`, :func:`write_csv`, :func:`plot_sweep`, :data:`SWEEP_FLAGS`, :func:`configure_parser`,
:func:`sweep_flags`, :func:`points_from_args`, :func:`run`, :func:`main`. A test that replaces one of them patches it in
its home module (``jaxrobo.training.sweep.running.GroupRunner``, ``jaxrobo.training.sweep.state.save_checkpoint``): the
name here is a second reference the sweep itself never reads.
"""
from __future__ import annotations

from jaxrobo.training.sweep.cli import SWEEP_FLAGS, configure_parser, main, points_from_args, run, sweep_flags
from jaxrobo.training.sweep.output import plot_sweep, write_csv
from jaxrobo.training.sweep.planning import (NOT_SWEPT, KeyKind, PlannedGroup, SweepPlan, classify, grid_points,
                                    parse_grid, parse_ranges, plan_groups, plan_sweep, random_points)
from jaxrobo.training.sweep.running import METRICS, GroupRunner, SweepInterrupted, SweepResult, run_plan, run_sweep
from jaxrobo.training.sweep.state import (STATE_FILE, STATE_FORMAT, code_version, load_checkpoint, open_state,
                                 read_state, save_checkpoint)

__all__ = ["METRICS", "NOT_SWEPT", "STATE_FILE", "STATE_FORMAT", "SWEEP_FLAGS", "GroupRunner", "KeyKind",
           "PlannedGroup", "SweepInterrupted", "SweepPlan", "SweepResult", "classify", "code_version",
           "configure_parser", "grid_points", "load_checkpoint", "main", "open_state", "parse_grid", "parse_ranges",
           "plan_groups", "plan_sweep", "plot_sweep", "points_from_args", "random_points", "read_state", "run",
           "run_plan", "run_sweep", "save_checkpoint", "sweep_flags", "write_csv"]
