"""Scale-out: shard a batch axis (sweep configurations, or a training run's environments) over devices and hosts.

Every row of a batch (one sweep configuration × seed, or one environment with its own table) is independent,
so the batch axis is split over a 1-D :class:`jax.sharding.Mesh` of all devices with
``NamedSharding(mesh, P("batch"))`` and XLA runs each device's slice with no communication; the results are
the same numbers as the unsharded run. Leaves without the batch axis (a shared table, scalars) are replicated.

Several hosts: start the same command on every host after :func:`initialize_distributed` (see
``docs/scaling.md``); ``jax.devices()`` then lists every device of every host, each process feeds only its own
shards (:func:`put_batch`) and :func:`gather` brings the whole result to every process.
"""
from __future__ import annotations

import copy
import math
import os
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

AXIS = "batch"


def initialize_distributed(coordinator: str | None = None, num_processes: int | None = None,
                           process_id: int | None = None) -> bool:
    """Join a multi-host run; returns True if this is one (more than one process).

    Arguments default to ``$JAXROBO_COORDINATOR`` (``host:port`` of process 0), ``$JAXROBO_NUM_PROCESSES`` and
    ``$JAXROBO_PROCESS_ID``; with none of them set, JAX's own detection (SLURM, Open MPI, Cloud TPU) is tried
    only if ``$JAXROBO_DISTRIBUTED=auto``, else nothing is done (a single-host run).
    """
    try:
        from jax._src import distributed

        if distributed.global_state.client is not None:  # already joined (e.g. by the CLI)
            return jax.process_count() > 1
    except (ImportError, AttributeError):
        pass
    from jaxrobo.core.environ import _check_port_free, check_coordinator, env_int

    coordinator = coordinator or os.environ.get("JAXROBO_COORDINATOR")
    if num_processes is None and os.environ.get("JAXROBO_NUM_PROCESSES"):
        num_processes = env_int("JAXROBO_NUM_PROCESSES", 1)
    if process_id is None and os.environ.get("JAXROBO_PROCESS_ID"):
        process_id = env_int("JAXROBO_PROCESS_ID", 0)
    if num_processes is not None and process_id is not None and not 0 <= process_id < num_processes:
        raise ValueError(f"JAXROBO_PROCESS_ID={process_id}: must be in 0..{num_processes - 1} "
                         f"(JAXROBO_NUM_PROCESSES={num_processes})")
    if coordinator is None and num_processes is None and process_id is None:
        if os.environ.get("JAXROBO_DISTRIBUTED", "").lower() != "auto":
            return False
        jax.distributed.initialize()
    else:
        if coordinator is None or num_processes is None or process_id is None:
            raise ValueError("multi-host: set all of JAXROBO_COORDINATOR (host:port), JAXROBO_NUM_PROCESSES and "
                             f"JAXROBO_PROCESS_ID (got {coordinator!r}, {num_processes!r}, {process_id!r})")
        check_coordinator(coordinator)
        if process_id == 0:  # JAX's service cannot start on a taken port: say so before it tries
            _check_port_free(coordinator)
        # Bounded: a coordinator that never answers is an error after this long, not a silent wait.
        timeout = env_int("JAXROBO_INIT_TIMEOUT", 1, default=INIT_TIMEOUT_SECONDS)
        try:
            with _recoverable_join():
                jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                                           process_id=process_id, initialization_timeout=timeout)
        except Exception as err:  # noqa: BLE001 - JAX raises RuntimeError or its own runtime error types here
            who = ("this process (0) serves the coordinator; the other processes did not connect" if process_id == 0
                   else f"process {process_id} could not register with the coordinator")
            # (JAX's message is at times only the name of a C++ exception, which says nothing to a user.)
            detail = "" if str(err).startswith("std::") else f" ({type(err).__name__}: {err})"
            raise JoinError(f"JAXROBO_COORDINATOR={coordinator!r}: the {num_processes} processes "
                            f"(JAXROBO_NUM_PROCESSES) did not all join within JAXROBO_INIT_TIMEOUT={timeout} s: "
                            f"{who}{detail}") from None
    return jax.process_count() > 1


class JoinError(RuntimeError):
    """``jax.distributed.initialize`` failed (a process never joined, or no coordinator answered) within
    ``$JAXROBO_INIT_TIMEOUT``. JAX's half-joined runtime stays as it is: tearing it down logs native errors and
    tracebacks at exit, so a command says the message and ends the process with :func:`exit_after_join_error`."""


def exit_after_join_error(prog: str, err: JoinError) -> None:
    """Say ``err`` in one line on stderr and end the process with status 2 at once (no teardown of JAX's
    distributed runtime, see :class:`JoinError`)."""
    import sys

    print(f"{prog}: {err}", file=sys.stderr)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(2)


class _ClientWithCallback:
    """JAX's native module as ``jax._src.distributed`` uses it, except that its distributed-runtime client gets a
    ``missed_heartbeat_callback``: without one, a join that times out ends the process with a native check
    failure (SIGABRT) from the client's error-polling thread; with one, ``connect()`` raises instead."""

    def __init__(self, native: Any):
        self._native = native

    def __getattr__(self, name: str) -> Any:
        return getattr(self._native, name)

    def get_distributed_runtime_client(self, *args: Any, **kwargs: Any) -> Any:
        kwargs.setdefault("missed_heartbeat_callback", _fatal_after_join)
        return self._native.get_distributed_runtime_client(*args, **kwargs)


def _fatal_after_join(*status: Any) -> None:
    """A process of a joined run died or lost contact: what JAX's own callback does (end this one), in one line."""
    import sys

    print(f"jaxrobo: the JAX distributed service reported a fatal error (a process of the run died or lost "
          f"contact): {status}", file=sys.stderr, flush=True)
    os._exit(1)


class _recoverable_join:
    """For the block, ``jax._src.distributed`` builds its client through :class:`_ClientWithCallback` (where that
    module's layout is the one this was written for, JAX 0.10; elsewhere nothing changes)."""

    def __enter__(self) -> None:
        try:
            from jax._src import distributed

            native = distributed._jax
        except (ImportError, AttributeError):
            self._module = None
            return
        if not callable(getattr(native, "get_distributed_runtime_client", None)):
            self._module = None
            return
        self._module, self._native = distributed, native
        distributed._jax = _ClientWithCallback(native)

    def __exit__(self, *_exc: Any) -> None:
        if self._module is not None:
            self._module._jax = self._native


#: Seconds ``jax.distributed.initialize`` waits for every process to join (``$JAXROBO_INIT_TIMEOUT``).
INIT_TIMEOUT_SECONDS = 120


def make_mesh(devices: list | None = None) -> Mesh:
    """A 1-D mesh named ``batch`` over the given devices (default: every device of every process)."""
    devices = list(jax.devices()) if devices is None else list(devices)
    return Mesh(np.asarray(devices), (AXIS,))


def padded_size(n: int, mesh: Mesh | None) -> int:
    """``n`` rounded up to a multiple of the number of devices."""
    if mesh is None:
        return n
    d = mesh.devices.size
    return int(math.ceil(n / d) * d)


def pad_rows(tree: Any, n: int) -> Any:
    """Host arrays padded along axis 0 to ``n`` rows by repeating the last row (padding rows are dropped later)."""
    def pad(x):
        x = np.asarray(x)
        if x.shape[0] == n:
            return x
        extra = np.repeat(x[-1:], n - x.shape[0], axis=0)
        return np.concatenate([x, extra], axis=0)

    return jax.tree.map(pad, tree)


def batch_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P(AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P())


def shardings_like(tree: Any, mesh: Mesh, batch: int) -> Any:
    """A sharding per leaf: split along axis 0 where that axis has length ``batch``, replicated otherwise."""
    def pick(x):
        shape = getattr(x, "shape", ())
        return batch_sharding(mesh) if len(shape) >= 1 and shape[0] == batch else replicated(mesh)

    return jax.tree.map(pick, tree)


def put_batch(tree: Any, mesh: Mesh | None) -> Any:
    """Host arrays with a leading batch axis → device arrays split over the mesh (each process gives its part).

    Without a mesh, a plain ``device_put`` to the default device.
    """
    if mesh is None:
        return jax.tree.map(jnp.asarray, tree)
    sharding = batch_sharding(mesh)

    def put(x):
        x = np.asarray(x)
        if x.shape[0] % mesh.devices.size:
            raise ValueError(f"batch of {x.shape[0]} rows does not split over {mesh.devices.size} devices; "
                             "pad it with pad_rows(padded_size(...)) first")
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree.map(put, tree)


def gather(tree: Any) -> Any:
    """Device arrays (sharded or not, one host or several) → numpy arrays on this host. Under ``jax.distributed``
    an array over every process's devices is gathered whole; one on this process's devices alone (a program's
    output that XLA left on one local device, as QuadcopterGoto-v2's progress read) is this process's value as it
    is: gathered, each process's copy was stacked (a scalar became one value per process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        def one(x: Any) -> Any:
            if isinstance(x, jax.Array) and x.is_fully_addressable:
                return np.asarray(jax.device_get(x))
            return multihost_utils.process_allgather(x, tiled=True)

        return jax.tree.map(one, tree)
    return jax.device_get(tree)


def largest(*values: int) -> tuple[int, ...]:
    """Each of this process's integers as the largest any process holds (under ``jax.distributed``; one process:
    as they are). A collective: every process calls it at the same point. For the decisions each process makes on
    its own (a signal that reached it, its clock) that every process must act on alike, or one of them runs the
    next collective alone."""
    if jax.process_count() == 1:
        return tuple(int(v) for v in values)
    from jax.experimental import multihost_utils

    got = np.asarray(multihost_utils.process_allgather(np.asarray(values, np.int32)))
    return tuple(int(v) for v in got.reshape(-1, len(values)).max(axis=0))


def specs_like(tree: Any, batch: int) -> Any:
    """A :class:`PartitionSpec` per leaf, as :func:`shardings_like` places it: ``P("batch")`` where axis 0 has
    length ``batch``, ``P()`` otherwise."""
    def pick(x):
        shape = getattr(x, "shape", ())
        return P(AXIS) if len(shape) >= 1 and shape[0] == batch else P()

    return jax.tree.map(pick, tree)


#: XLA passes left out of a program compiled for several devices (:func:`spmd_options`), by the devices'
#: platform. On a CPU, XLA's partitioner ends with a clean-up that eliminates common subexpressions before the
#: simplification every program goes through; a program for one device meets that elimination only later, after
#: the simplifier has rewritten the duplicates one by one. The two orders fused and rounded differently: a
#: sweep's returns moved in their last bits between one device and several (forced CPU devices; the loop of a Goto
#: step alone shows it), and without the early elimination they round as one device's do. A GPU is the other way
#: round: its pipeline runs CSE where the one-device program does too, and leaving the passes out is what made two
#: H200s round differently from one (a Goto-v2 sweep, 1,024 rows: 1,641 of 1.3 M recorded returns moved in their
#: last bits; with the passes kept, every return is the one-device return, and the program compiles ~7 s sooner).
SPMD_DISABLED_PASSES: dict[str, tuple[str, ...]] = {"cpu": ("cse",)}


def spmd_options(options: dict[str, Any] | None, mesh: Mesh | None) -> dict[str, Any] | None:
    """``options`` (XLA compiler options, or None) for a program split over ``mesh``: with more than one device,
    the passes :data:`SPMD_DISABLED_PASSES` names for their platform added to ``xla_disable_hlo_passes`` (with
    those already there); else as given."""
    if mesh is None or mesh.devices.size == 1:
        return options
    passes = SPMD_DISABLED_PASSES.get(mesh.devices.flat[0].platform, ())
    if not passes:
        return options
    out = dict(options or {})
    given = [p for p in str(out.get("xla_disable_hlo_passes", "")).split(",") if p]
    out["xla_disable_hlo_passes"] = ",".join(dict.fromkeys(given + list(passes)))
    return out


def jit_batched(fn: Callable, mesh: Mesh | None, batch: int, example_args: tuple, donate: tuple[int, ...] = (),
                compiler_options: dict[str, Any] | None = None) -> Callable:
    """``jax.jit(fn)`` with every argument and result split along its batch axis over ``mesh`` (if any).

    ``fn`` must treat its rows independently (a ``vmap``). Over a mesh it runs under ``shard_map``: every device
    executes ``fn`` traced for its own ``batch / devices`` rows, with no communication, and the program is
    compiled once for the whole mesh, under :func:`spmd_options`, so that its rows round as one device's do."""
    if mesh is None:
        return jax.jit(fn, donate_argnums=donate, compiler_options=compiler_options)
    compiler_options = spmd_options(compiler_options, mesh)
    out = jax.eval_shape(fn, *example_args)
    local = jax.shard_map(fn, mesh=mesh, in_specs=specs_like(example_args, batch), out_specs=specs_like(out, batch),
                          check_vma=False)
    return jax.jit(local, in_shardings=shardings_like(example_args, mesh, batch),
                   out_shardings=shardings_like(out, mesh, batch), donate_argnums=donate,
                   compiler_options=compiler_options)


class ShardedTrainer:
    """A :class:`jaxrobo.training.trainer.Trainer` whose ``n_envs`` environments are split over the devices of a mesh.

    ``init`` / ``run_chunk`` are jitted with the Runner's env axis sharded (a shared table is replicated and
    its batched update becomes a cross-device reduction). ``n_envs`` must be a multiple of the device count.
    """

    def __init__(self, trainer: Any, mesh: Mesh | None = None):
        self.trainer = trainer
        self.mesh = make_mesh() if mesh is None else mesh
        n, d = trainer.config.n_envs, self.mesh.devices.size
        if n % d:
            raise ValueError(f"n_envs={n} must be a multiple of the {d} devices to shard environments over them")
        if d > 1 and trainer.env_group is not None:
            # Stepping the env axis group after group would slice across the devices' shards: each device steps
            # its own n_envs / d envs at once instead (the same values).
            self.trainer = trainer = copy.copy(trainer)
            trainer.env_group = None
        self._init = None
        self._chunk = None

    def init(self, key: jax.Array, agent_params: Any, env_params: Any) -> Any:
        if self._init is None:
            out = jax.eval_shape(self.trainer.init, key, agent_params, env_params)
            self._init = jax.jit(self.trainer.init, out_shardings=shardings_like(out, self.mesh,
                                                                                  self.trainer.config.n_envs))
        return self._init(key, agent_params, env_params)

    def run_chunk(self, runner: Any, agent_params: Any, env_params: Any) -> Any:
        if self._chunk is None:
            s = shardings_like(runner, self.mesh, self.trainer.config.n_envs)
            rep = replicated(self.mesh)
            self._chunk = jax.jit(self.trainer.run_chunk, donate_argnums=0,
                                  in_shardings=(s, jax.tree.map(lambda _: rep, agent_params),
                                                jax.tree.map(lambda _: rep, env_params)),
                                  out_shardings=s)
        return self._chunk(runner, agent_params, env_params)
