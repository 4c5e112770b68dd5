"""The execution plan: every choice that changes how fast a run goes and never what it computes.

A run's speed choices (how many envs are stepped at once, whether MJX's inertia stage is replaced, how done envs are
reset, whether table rows are carried, the XLA options) live in one frozen :class:`ExecutionPlan`, built once from the
device and the run's config by :meth:`ExecutionPlan.for_run` and passed explicitly to whatever traces the run:
:class:`jaxrobo.training.trainer.Trainer` (and so :func:`jaxrobo.training.train.train`), the sweep's compiled groups,
:class:`jaxrobo.interop.gym_adapter.JaxroboVectorEnv`, the benchmarks. Every choice gives the same values bit for bit
(the tests compare them); what changes is the program XLA compiles (exceptions found: on a CPU, XLA rounds the
quadcopter's step by the batch it is given, so ``env_group`` and ``devices`` may move its last bits there, and on GPUs
``devices`` moves them: docs/scaling.md). There are no module-global knobs: to measure another choice, build another
plan (``plan.replace(lean_mjx=False)``).

The plan acts while a program is traced: its fields are read by the code that builds the step (:func:`step_batch`, the
trainer's step), and the one choice that sits deep under the pure ``env.step(state, action, params)``, the MJX stage
replacement, travels with :meth:`ExecutionPlan.tracing`, a block during which the simulator asks
:func:`jaxrobo.physics.mjx_lean.wanted` (see :mod:`jaxrobo.physics.mjx_lean`). A jitted function traced once keeps the
plan it was traced under, so build one jitted function per plan (a :class:`~jaxrobo.training.trainer.Trainer` per plan
does that). ``repr(plan)`` is short, names every choice, and is the plan's tag in benchmark rows and run summaries.
JAX's persistent compilation cache keys on the lowered program, so two plans never share a cached executable unless they
lower to the same program. A checkpoint does not record the plan: the values do not depend on it (a carry written under
one plan goes on under another, as long as the carry's structure, which ``carry_rows`` changes, is the same; the
checkpoint checks that).

Public surface: :class:`ExecutionPlan` (fields, :meth:`~ExecutionPlan.for_run`, :meth:`~ExecutionPlan.replace`,
:meth:`~ExecutionPlan.partitioned`, :meth:`~ExecutionPlan.tracing`, :meth:`~ExecutionPlan.traced`,
:attr:`~ExecutionPlan.xla_options`, :meth:`~ExecutionPlan.to_dict`), :func:`default_env_group`, :func:`default_fused`,
:func:`physics_kernel`, :func:`task_kernel`, :func:`chunk_kernel_refusal`, :func:`check_pallas`, :func:`step_batch`
(``env.step`` over a batch, as the plan groups it) and :func:`map_groups` (any row-independent function, group after
group).
Names with a leading underscore are private.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, Callable, Iterator, Mapping

import jax

from jaxrobo.physics import fused as _fused
from jaxrobo.physics import mjx_lean
from jaxrobo.core import hash_kernel as _hash_kernel
from jaxrobo.speed import reuse as _reuse
from jaxrobo.core.config import ConfigError
from jaxrobo.task.env import Env, EnvState, layers, shared_resets, simulator_of

#: Envs stepped at once on a GPU when the env runs on MJX: beyond this size a step's intermediates no longer fit
#: the GPU's L2 cache and larger batches ran slower as one batch than as groups of this size (a reading, not
#: profiled; the measurements are in docs/results.md, ``env_groups.json``).
_GPU_ENV_GROUP = 262_144


def default_devices(config: Any) -> int:
    """Devices a training run's envs are split over: the config's ``devices`` (refused if it does not divide
    ``n_envs`` or exceeds the devices there are), or for 0 (automatic) every device JAX sees (of every process
    under ``jax.distributed``), or the most of them that divide ``n_envs``."""
    asked = int(getattr(config, "devices", 1) or 0)
    available = jax.device_count()
    n = int(config.n_envs)
    if asked:
        if asked > available:
            raise ConfigError(f"devices={asked}: only {available} device(s) here ({jax.devices()[0].platform})")
        if n % asked:
            raise ConfigError(f"devices={asked}: must divide n_envs={n} (each device steps n_envs / devices envs)")
        return asked
    return max(d for d in range(1, available + 1) if n % d == 0)


def default_env_group(env: Env, backend: str | None = None) -> int | None:
    """How many envs :func:`step_batch` steps at once when the config leaves it automatic: 262,144 for MJX on a
    GPU, otherwise None (the whole batch). Not for Brax's pipelines, which ran slower in groups, nor for a closed
    form (one fused kernel) or a CPU (nothing measurable to gain). ``backend``: JAX's platform name (default:
    ``jax.default_backend()``)."""
    backend = jax.default_backend() if backend is None else backend
    sim = simulator_of(env)
    if backend == "gpu" and sim is not None and sim.backend == "mjx":
        return _GPU_ENV_GROUP
    return None


#: Fewest envs a GPU run has for :func:`default_fused` to write out many substeps or run a Pallas kernel: from
#: 1,024 envs they ran faster per step (measured); the default Goto preset's 64 envs took twice the wall time (the
#: written-out physics compiles ~9 s longer, which a run that small does not earn back).
_FUSED_MIN_ENVS = 1024


#: Fewest envs for which :func:`default_fused` picks the cart-pole's whole-chunk Pallas kernel: it compiles ~18 s
#: longer on first use, which a run of a few thousand envs does not earn back (H200, the default cart-pole command
#: at 4,096 envs, whole command from start to exit: kernel 28.3 s with an empty cache and 5.1 s warm, training 0.8 s;
#: without it 11.7-12.0 s and 5.6-6.7 s, training 0.9-1.2 s warm; benchmarks/results/h200/time_to_trained.json).
_CHUNK_KERNEL_MIN_ENVS = 16_384


#: Fewest envs a GPU run under ``fused="pallas"`` has for :meth:`ExecutionPlan.for_run` to gather its done envs
#: for the reset: the smallest batch where that was measured faster (docs/benchmarks.md, "Pallas: quadcopter").
_GATHER_MIN_ENVS = 262_144


#: The values of ``ExecutionPlan.fused``: :mod:`jaxrobo.physics.fused`'s, and ``"pallas"`` (:func:`check_pallas`).
FUSED_CHOICES = _fused.CHOICES + ("pallas",)


def physics_kernel(env: Env) -> bool:
    """Whether ``env``'s robot offers its control step as a kernel (:attr:`jaxrobo.task.robot.Robot.advance_kernel`:
    the quadcopter on backend ``rigid``), which ``fused="pallas"`` runs while the rest of the step stays XLA's."""
    robot = getattr(layers(env)[-1], "robot", None)
    return getattr(robot, "advance_kernel", None) is not None


def task_kernel(env: Env) -> bool:
    """Whether ``env``'s task offers its whole step as a kernel (``step_kernel``: the Goto tasks on backend
    ``rigid``, :mod:`envs.quadcopter.goto_kernel`), which ``fused="pallas"`` with ``task_kernel`` runs."""
    return getattr(layers(env)[-1], "step_kernel", None) is not None


def chunk_kernel_refusal(env: Env, config: Any, agent: str | None = None, discretiser: Any = None,
                         fused_block: int | None = None) -> str | None:
    """Why training ``env`` with ``config`` (a :class:`jaxrobo.training.trainer.TrainConfig`) cannot run its
    chunks as the task's one kernel (:attr:`jaxrobo.task.env.TaskEnv.chunk_kernel`: the analytic cart-pole with
    Q-learning, :mod:`envs.cartpole.kernel`); None: it can. The task's own rules, read both by the plan's default
    (:func:`default_fused`) and by the boundary that refuses an explicit choice (:func:`check_pallas`). ``agent``:
    the learner's name (default: ``config.agent``); ``discretiser``: the run's
    :class:`jaxrobo.tabular.discretise.Discretiser` (default: the config's, built only for a task with a kernel);
    ``fused_block``: the plan's envs per program."""
    kernel = getattr(type(env), "chunk_kernel", None)  # the class's: a wrapper forwards attributes, not its step
    if kernel is None:
        return f"the env is {type(env).__name__}, whose task offers no whole-chunk kernel"
    if discretiser is None:
        from jaxrobo.tabular.discretise import make_discretiser_for

        discretiser = make_discretiser_for(env, config)
    return kernel.unsupported_run(env, config, config.agent if agent is None else agent, discretiser, fused_block)


def check_pallas(trainer: Any) -> None:
    """Refuse (a :class:`jaxrobo.core.config.ConfigError`, naming the field and the runs it supports) a
    :class:`jaxrobo.training.trainer.Trainer` whose run ``fused="pallas"`` cannot take. Two runs can: a robot with a
    physics kernel (:func:`physics_kernel`), with any learner, and a task whose whole chunk is one kernel (the
    analytic cart-pole with Q-learning, :func:`chunk_kernel_refusal`)."""
    if trainer.plan.task_kernel and not task_kernel(trainer.env):
        inner = layers(trainer.env)[-1]
        why = getattr(inner, "step_kernel_refusal", None)  # the task's reason, where it names one
        raise ConfigError(f"ExecutionPlan task_kernel=True: {type(inner).__name__} has no kernel for its whole step"
                         f"{f' ({why})' if why else ''}; the Goto tasks with discrete actions on backend='rigid' "
                         "have one. Set task_kernel=False (the control step alone runs as a kernel where the "
                         "robot has one)")
    if physics_kernel(trainer.env):
        if trainer.plan.fused_block is not None:
            raise ConfigError(f"ExecutionPlan fused='pallas': fused_block={trainer.plan.fused_block}; the "
                             f"{type(trainer.env).__name__} control-step kernel sets its own envs per program: "
                             "leave fused_block None")
        return
    why = chunk_kernel_refusal(trainer.env, trainer.config, trainer.learner.name, trainer.disc,
                               trainer.plan.fused_block)
    if why is not None:
        raise ConfigError(f"ExecutionPlan fused='pallas': {why}. It supports the quadcopter tasks on backend='rigid' "
                         "(the control step as one kernel, any learner) and the analytic CartPoleStayUp with "
                         "Q-learning (the whole chunk as one kernel); use fused='off' or 'xla' otherwise")


def default_fused(env: Env, backend: str | None = None, n_envs: int | None = None, *, config: Any = None,
                  agent: str | None = None, discretiser: Any = None, devices: int | None = None) -> str:
    """The fused choice for training ``n_envs`` envs of ``env`` on ``backend``, split over ``devices`` (default: every
    device JAX sees). On a GPU, from 1,024 envs: ``"pallas"`` from 16,384 envs (:data:`_CHUNK_KERNEL_MIN_ENVS`) for a
    run whose whole chunk is one kernel (the analytic cart-pole with Q-learning, :mod:`envs.cartpole.kernel`: 10.5-17.7x
    the env steps/s of the plain path on an H100 at 1 k-1 M envs; it compiles ~10-25 s longer, which a short run
    compiling cold does not earn back; the persistent compile cache serves the later runs of a configuration,
    docs/benchmarks.md, "Pallas"), decided from ``config`` (a :class:`jaxrobo.training.trainer.TrainConfig`; its
    ``n_envs`` replaces ``n_envs``) with the run's learner name ``agent`` and ``discretiser`` (defaults: the config's)
    by :func:`chunk_kernel_refusal`, the rules that also refuse an explicit choice. Otherwise, with a closed form of
    more substeps per control step than the plain path writes out (8): ``"pallas"`` where the robot offers its control
    step as a kernel (:func:`physics_kernel`: the rigid quadcopter, whose Goto + Q-learning ran 2.9-3.9x the env steps/s
    of ``"xla"`` on an H100 at 1 k-1 M envs and compiled faster) and the run is on one device (XLA cannot split that
    kernel's custom call over several; the whole-chunk kernel runs on each device's envs under ``shard_map``), else
    ``"xla"`` (the substeps written out: 1.3x the rolled loop at 1 k-262 k envs, 1.6x at 1 M). ``"off"`` otherwise: on 2
    CPU cores they ran at the same speed and took longer to compile, small runs do not earn back the longer compile, and
    with 8 substeps or fewer the program is the same. A run the kernels cannot take keeps these choices; blocks of envs
    (``fused_block``) are never defaults (docs/benchmarks.md, "Fused path" and "Pallas"). ``backend``: JAX's platform
    name (default: ``jax.default_backend()``); ``n_envs`` and ``config`` None (stepping envs outside training):
    ``"off"``."""
    backend = jax.default_backend() if backend is None else backend
    n_envs = config.n_envs if config is not None else n_envs
    big = n_envs is not None and n_envs >= _FUSED_MIN_ENVS
    if not (big and backend == "gpu"):
        return "off"
    # The control-step kernel, a custom call inside the step, only where the run is on one device: XLA cannot
    # partition it. The whole-chunk kernel runs on each device's envs under shard_map (driver.compiled_chunk).
    one = (jax.device_count() if devices is None else devices) == 1
    if config is not None and not physics_kernel(env) and n_envs >= _CHUNK_KERNEL_MIN_ENVS:
        if chunk_kernel_refusal(env, config, agent, discretiser) is None:
            return "pallas"
    sim = simulator_of(env)
    many = sim is not None and getattr(sim, "cheap_step", False) and int(getattr(sim, "n_substeps", 1) or 1) > 8
    if not many:
        return "off"
    return "pallas" if physics_kernel(env) and one else "xla"


@dataclasses.dataclass(frozen=True, repr=False)
class ExecutionPlan:
    """How a run is executed; every choice keeps the values bit for bit.

    ``env_group``: envs stepped at once by :func:`step_batch` (None: the whole batch as one ``vmap``); a larger
    batch runs as consecutive groups of this many envs. Only the env step is grouped: the learner's work is cheap
    per env and grouping it would copy each group's tables out and back.

    ``unrolled_groups``: how many groups :func:`map_groups` writes out with static slices, which XLA fuses into
    the code around them without a loop; more run in a loop over blocks of this many. Each group written out is
    one more copy of the step to compile, so this trades compile time for speed.

    ``lean_mjx``: trace MJX steps with the stage replacement of :mod:`jaxrobo.physics.mjx_lean` (a no-op where it does
    not apply).

    ``reset_capacity``: most done envs a training step resets by gathering them, resetting them and scattering
    them back; a step with more resets the whole batch. A reset under ``vmap`` costs a physics state and random
    draws in every env although few are done, so gathering them pays where envs are expensive one by one (a CPU);
    equal to ``n_envs`` (or None: every env) it is the plain select, cheaper where the gather/scatter and the
    branch cost more than the resets they save (an accelerator whose env step is itself batch-wide XLA work). With
    the physics in a kernel (``fused="pallas"``) the task's reset is a large share of what is left, and gathering
    pays on a GPU too at large batches.

    ``carry_rows``: carry each env's table rows at its state in the training carry, so a step reads the tables
    once instead of three times. That pays where the reads are cache misses (a CPU); on an accelerator the reads
    are cheap and XLA may copy the whole tables each step to keep the rows from before the update, and with a
    shared table other envs' updates would make the carried rows stale.

    ``fused``: ``"off"``, ``"xla"`` or ``"pallas"``. ``"xla"``: the fused training path of :mod:`jaxrobo.physics.fused`:
    a closed form's physics substeps all written out, and with ``fused_block`` the chunk's steps run inside blocks of
    that many envs. ``"pallas"``: a Pallas kernel, for two kinds of run (``Trainer`` refuses the others, naming the
    field: :func:`check_pallas`): the rigid quadcopter's control step (controller and physics substeps) as one kernel
    over the batch (:mod:`envs.quadcopter.kernel`, any learner; the rest of the step is XLA's), and the analytic
    cart-pole's whole chunk with Q-learning and per-env tables (:mod:`envs.cartpole.kernel`). ``fused_block``: with
    ``fused="xla"``, envs per block (None: the whole batch, no blocking), read only with per-env tables (a shared table
    mixes every env each step, so it runs unblocked); bit for bit on a CPU, while on a GPU the written-out substeps may
    round a last bit differently (see :mod:`jaxrobo.physics.fused`). With ``fused="pallas"`` on the cart-pole, envs per
    Pallas program (a power of two up to 1024; None: one warp's 32, :data:`envs.cartpole.kernel.BLOCK`); the
    quadcopter's kernel sets its own block, so it refuses one.

    ``skip_resets``, ``group_resets``, ``fast_sincos``: read only by a whole-chunk kernel (the cart-pole's), each
    keeping every value (the tests compare them with the choice off). ``skip_resets``: a program hashes the
    reset's random numbers and gathers the fresh rows only in a step where one of its envs is done (a scalar branch
    per program); off, in every env every step, selected away where not done. ``group_resets`` (with
    ``skip_resets``): a program whose done envs number at most a quarter of its lanes hashes their resets in groups
    of four lanes (under domain randomisation at most an eighth, in groups of eight); off, each lane its own env's.
    ``fast_sincos``: on a GPU where :func:`jaxrobo.physics.libdevice_sincos.verified`, in a step where every pole
    angle of a program stays within the written-out ``sin``/``cos``'s range (one scalar branch per program and
    step), those instead of libdevice's calls; off, and off a GPU, the calls.

    ``task_kernel``: with ``fused="pallas"``, a task that offers its whole step as a kernel (the Goto tasks'
    ``step_kernel``, :mod:`envs.quadcopter.goto_kernel`: action, control step, observation, outcome, reward and the
    NaN guard in one call) runs that instead of the robot's control-step kernel with the rest of the step in XLA;
    equal to float32 round-off. :meth:`for_run` turns it on with ``fused="pallas"`` where the task has one; a
    plan with it on for a task without one is refused (:func:`check_pallas`). Read only under ``fused="pallas"``.

    ``ordered_sums``: a shared table sums the updates that meet in one entry in a fixed order
    (:func:`jaxrobo.tabular.learner.sum_in_order`: sort, segmented scan) instead of a scatter-add, which a GPU runs as
    float atomics in no fixed order: there the same seed gave other tables run after run. The default on a GPU
    with a shared table; elsewhere the scatter-add, which a CPU runs in order (its rounding is the one the
    fingerprints hold). The one plan choice that may change values: it rounds the sums in another order.

    ``devices``: how many devices a training run's envs are split over (1: one device). Each device steps its
    ``n_envs / devices`` envs with no communication (per-env tables; a shared table's update and a run-wide
    budget's episode count become cross-device reductions), so per-env tables are the one-device ones bit for
    bit; under ``jax.distributed`` the devices of every process count. With several devices the env axis is not
    also stepped in groups (``env_group`` None): each device steps its share at once.

    ``compile_beside``: a training run compiles its first carry's program (the envs' reset) and its greedy
    evaluation (which the learning-target checks fly too) in threads beside the training chunk, from the carry's
    shapes, not before and after it (then the evaluation beside the first chunks' training). The chunk, whose
    XLA compile is the longest, is traced first and compiled in a thread; the evaluation is traced after it and
    compiled beside it, and the small programs that pick the evaluated tables and their keys in another thread.
    XLA compiles outside Python's lock, so on a host with cores to spare a first run's compiles overlap instead
    of its chunk waiting for the reset's and its first check for the evaluation's; on 2 CPU cores the compiles and
    the first chunks share the cores either way, and the first runs gained at most 0.9 s (the arm) or lost up to
    0.5 s (Goto-v2; ``benchmarks/results/cpu-2cores/compile_beside_cpu.json``). On by default on a GPU. The
    programs are the same either way.

    ``reuse_traces``: keep the run's traced programs (training chunk, init, greedy evaluation) exported beside the
    persistent compilation cache, and read them back in a later process of the same configuration instead of
    tracing again (:mod:`jaxrobo.speed.reuse`, which says what the key holds, a function patched in at run time
    included, and what it cannot see: a patch inside JAX or another installed library). On by default for a run on
    one device where a compilation cache is in use (``JAXROBO_REUSE_TRACES=off`` turns it off); the programs are
    the same either way.

    ``fixed_kernels``: compile with XLA's GPU autotuning off (``xla_gpu_autotune_level`` 0), so each kernel takes
    XLA's default configuration instead of the one its compile timed fastest. The timings vary with the GPU's
    state, and a program's numbers varied with them: on an H200, QuadcopterGoto-v2's default run compiled after the
    cart-pole's and the arm's recorded 59 of its 2,048 first episodes' returns one ulp away from the run compiled
    alone (three calls); with autotuning off it recorded the run alone's, and the three tasks' default runs wrote
    the files they write with it on, as fast warm (``benchmarks/results/h200/autotune_off.json``). On by default
    on a GPU; no effect elsewhere.

    ``hash_kernel``: on a CUDA GPU, the random draws hash their counters with jaxlib's threefry kernel
    (:mod:`jaxrobo.core.hash_kernel`) instead of the hash's integer ops fused into the step: the same bits, a
    smaller program to compile (QuadcopterGoto-v2's default on an H200: 6.2-7.1 -> 4.1-4.6 s cold), a slower step
    at large batches (27 % at 65,536 Goto-v2 envs). On by default for a run on one GPU of up to
    :data:`jaxrobo.core.hash_kernel.MAX_ENVS` envs (a sweep's rows on one GPU too); elsewhere (several devices,
    whose partitioned program cannot split the kernel's call; where the kernel is unavailable) the ops.

    ``compiler_options``: XLA options for the run's compiles, as sorted ``(name, value)`` pairs (a mapping is
    accepted and sorted), or None for XLA's defaults. Tests lower the optimisation level to compile faster.
    """

    env_group: int | None = None
    unrolled_groups: int = 4
    lean_mjx: bool = True
    reset_capacity: int | None = None
    carry_rows: bool = False
    fused: str = "off"
    fused_block: int | None = None
    task_kernel: bool = False
    skip_resets: bool = True
    group_resets: bool = True
    fast_sincos: bool = True
    ordered_sums: bool = False
    devices: int = 1
    compile_beside: bool = False
    reuse_traces: bool = False
    fixed_kernels: bool = False
    hash_kernel: bool = False
    compiler_options: tuple[tuple[str, Any], ...] | None = None

    def __post_init__(self) -> None:
        if self.fused not in FUSED_CHOICES:
            raise ValueError(f"ExecutionPlan fused={self.fused!r}: allowed values are {', '.join(FUSED_CHOICES)}")
        for name in ("env_group", "reset_capacity", "fused_block"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
                raise ValueError(f"ExecutionPlan {name}={value!r}: expected None or an integer >= 1")
        if not isinstance(self.devices, int) or isinstance(self.devices, bool) or self.devices < 1:
            raise ValueError(f"ExecutionPlan devices={self.devices!r}: expected an integer >= 1")
        if not isinstance(self.unrolled_groups, int) or isinstance(self.unrolled_groups, bool) \
                or self.unrolled_groups < 1:
            raise ValueError(f"ExecutionPlan unrolled_groups={self.unrolled_groups!r}: expected an integer >= 1")
        for name in ("lean_mjx", "carry_rows", "task_kernel", "skip_resets", "group_resets", "fast_sincos",
                     "ordered_sums", "compile_beside", "reuse_traces", "fixed_kernels", "hash_kernel"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"ExecutionPlan {name}={getattr(self, name)!r}: expected True or False")
        options = self.compiler_options
        if options is not None:
            pairs = options.items() if isinstance(options, Mapping) else options
            try:
                options = tuple(sorted((str(k), v) for k, v in pairs))
                hash(options)
            except (TypeError, ValueError) as err:
                raise ValueError(f"ExecutionPlan compiler_options={self.compiler_options!r}: expected a mapping or "
                                 f"(name, value) pairs of hashable values ({err})") from None
            object.__setattr__(self, "compiler_options", options or None)

    @classmethod
    def for_run(cls, env: Env, config: Any = None, backend: str | None = None, *,
                compiler_options: Mapping[str, Any] | None = None, agent: str | None = None,
                discretiser: Any = None) -> "ExecutionPlan":
        """The plan for training ``env`` with ``config`` (a :class:`jaxrobo.training.trainer.TrainConfig`: its
        ``n_envs``, ``shared_table`` and ``env_group``) on ``backend`` (JAX's platform name; default
        ``jax.default_backend()``). Without a config (stepping envs outside training, e.g. the Gymnasium vector env)
        only the env grouping and the MJX stage matter: ``reset_capacity`` is None and rows are not carried. With a
        config, ``reset_capacity`` is an eighth of the batch on a CPU and under ``fused="pallas"`` with a physics kernel
        from 262,144 envs, the whole batch (the plain select) otherwise. ``fused``: the config's ``fused`` where it
        names one (``off``, ``xla``, ``pallas``), else (``auto``) :func:`default_fused`, which on a GPU from 1,024 envs
        picks ``"pallas"`` for a run the cart-pole's whole-chunk kernel or the quadcopter's control-step kernel takes;
        with ``devices`` automatic (0), a run that takes the control-step kernel on one device stays on one (the plan
        does not depend on the device count); ``agent`` (a learner's name) and ``discretiser`` (a
        :class:`jaxrobo.tabular.discretise.Discretiser`) are the run's where they differ from the config's (a
        :class:`jaxrobo.training.trainer.Trainer` given its own passes them). ``compiler_options``: see the class
        docstring (XLA's defaults unless given). ``ordered_sums`` is on for a shared table on a GPU, ``hash_kernel`` on
        one GPU up to :data:`jaxrobo.core.hash_kernel.MAX_ENVS` envs."""
        backend = jax.default_backend() if backend is None else backend
        cpu = backend == "cpu"
        if config is None:
            return cls(env_group=default_env_group(env, backend), compiler_options=compiler_options)
        # The config's fused, "auto" (or a config without the field) meaning the default for this device and run.
        asked = getattr(config, "fused", "auto")
        devices = default_devices(config)
        if devices > 1 and not getattr(config, "devices", 0) and config.shared_table:
            # One table fed by every env: split over devices, its update becomes a reduction across them, summed
            # in another order than on one device (Goto-v2's default tables differed between 1 and 4 forced CPU
            # devices). With devices automatic such a run stays on one, so its result does not depend on the count.
            devices = 1
        if asked == "auto":
            fused = default_fused(env, backend, config=config, agent=agent, discretiser=discretiser, devices=devices)
            if devices > 1 and not getattr(config, "devices", 0) and physics_kernel(env) and default_fused(
                    env, backend, config=config, agent=agent, discretiser=discretiser, devices=1) == "pallas":
                # One GPU with the control-step kernel, not several without it: the kernel cannot be split over
                # devices, and without it the step is written out (Goto-v2's default on an H200: 27 s of compile
                # against the kernel's ~11 s). So the automatic plan is the same on any device count.
                devices, fused = 1, "pallas"
        else:
            fused = asked
        # Gather the done envs (an eighth of the batch: few finish on any one step) on a CPU, and on a GPU where
        # the physics runs as a kernel and the batch is large: there the plain select's reset of every env (goal,
        # obstacles, a first observation with its ray tests) cost up to a fifth of the step (Goto-v2 on an H100,
        # 262 k and 1 M envs). Smaller GPU batches are latency-bound and the gather adds ~50 kernels a step (not
        # measured there); elsewhere on an accelerator the plain select. The cart-pole's whole-chunk kernel resets
        # in place and reads neither.
        gather = cpu or (fused == "pallas" and physics_kernel(env) and config.n_envs >= _GATHER_MIN_ENVS)
        return cls(
            # The config's env_group, 0 meaning automatic; none across devices (each steps its share at once).
            env_group=(config.env_group or default_env_group(env, backend)) if devices == 1 else None,
            devices=devices,
            reset_capacity=-(-config.n_envs // 8) if gather else config.n_envs,
            # Carried rows pay only on a CPU, and are wrong with a shared table (see the class docstring).
            carry_rows=cpu and not config.shared_table,
            fused=fused,
            # The whole task step as one kernel where the task has one: the observation, outcome and reward then
            # leave the batch-wide XLA kernels they took around the control step (docs/benchmarks.md, "Pallas:
            # quadcopter").
            task_kernel=fused == "pallas" and task_kernel(env),
            # A GPU sums a shared table's updates as float atomics in no fixed order: sum them in order there.
            ordered_sums=backend == "gpu" and config.shared_table,
            compile_beside=not cpu,
            reuse_traces=devices == 1 and _reuse.available(),
            fixed_kernels=backend == "gpu",
            # The hash as a kernel where a run is small enough that its compile, not its steps, is most of the wall;
            # on one device (a program XLA partitions over several cannot split a custom call).
            hash_kernel=backend == "gpu" and devices == 1 and config.n_envs <= _hash_kernel.MAX_ENVS
            and _hash_kernel.usable(),
            compiler_options=compiler_options,
        )

    def replace(self, **changes: Any) -> "ExecutionPlan":
        """A copy with some choices changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def partitioned(self, devices: int) -> "ExecutionPlan":
        """This plan for a program XLA partitions over ``devices`` (a sweep's rows split over a mesh): with several,
        ``hash_kernel`` off (the partitioner cannot split a custom call; the hash's ops give the same values)."""
        return self.replace(hash_kernel=False) if devices > 1 and self.hash_kernel else self

    @property
    def xla_options(self) -> dict[str, Any] | None:
        """``compiler_options`` as the dict ``jax.jit(..., compiler_options=...)`` takes (None: XLA's defaults), with
        ``fixed_kernels``' option first (an option given in ``compiler_options`` wins)."""
        options = {"xla_gpu_autotune_level": 0} if self.fixed_kernels else {}
        options.update(self.compiler_options or ())
        return options or None

    @contextlib.contextmanager
    def tracing(self) -> Iterator["ExecutionPlan"]:
        """A block whose traces follow this plan's trace-time choices (the MJX stage replacement, a closed form's
        substeps written out under ``fused``) and share each env's reset trace (:func:`jaxrobo.task.env.
        shared_resets`); nests, and is local to the thread or task that enters it."""
        with mjx_lean.choose(self.lean_mjx), _fused.choose(self.fused, self.task_kernel), \
                _hash_kernel.choose(self.hash_kernel), shared_resets():
            yield self

    def traced(self, fn: Callable) -> Callable:
        """``fn``, run inside :meth:`tracing`: ``jax.jit(plan.traced(fn))`` traces ``fn`` under this plan."""

        @functools.wraps(fn)
        def under_plan(*args: Any, **kwargs: Any) -> Any:
            with self.tracing():
                return fn(*args, **kwargs)

        return under_plan

    def to_dict(self) -> dict[str, Any]:
        """The choices as plain JSON values (``compiler_options`` as a dict)."""
        out = dataclasses.asdict(self)
        out["compiler_options"] = self.xla_options
        return out

    def __repr__(self) -> str:
        def on(flag: bool) -> str:
            return "on" if flag else "off"

        parts = [f"env_group={'all' if self.env_group is None else self.env_group}",
                 f"unrolled_groups={self.unrolled_groups}", f"lean_mjx={on(self.lean_mjx)}",
                 f"reset_capacity={'all' if self.reset_capacity is None else self.reset_capacity}",
                 f"carry_rows={on(self.carry_rows)}"]
        if self.fused != "off":  # named only when on, so plans from before the choice read as they did
            block = "all" if self.fused_block is None else self.fused_block
            parts.append(f"fused={self.fused}, fused_block={block}")
            if self.fused == "pallas" and self.task_kernel:
                parts.append("task_kernel=on")
            # The whole-chunk kernel's choices, named only when off (a plan as the default prints as it did).
            parts += [f"{name}=off" for name in ("skip_resets", "group_resets", "fast_sincos")
                      if self.fused == "pallas" and not getattr(self, name)]
        if self.compile_beside:  # likewise
            parts.append("compile_beside=on")
        if self.ordered_sums:  # likewise
            parts.append("ordered_sums=on")
        if self.reuse_traces:  # likewise
            parts.append("reuse_traces=on")
        if self.fixed_kernels:
            parts.append("fixed_kernels=on")
        if self.hash_kernel:
            parts.append("hash_kernel=on")
        if self.devices > 1:  # likewise
            parts.append(f"devices={self.devices}")
        if self.compiler_options is not None:
            parts.append("compiler_options={" + ", ".join(f"{k}: {v!r}" for k, v in self.compiler_options) + "}")
        return f"ExecutionPlan({', '.join(parts)})"


# ---- stepping a batch ------------------------------------------------------------------------------------------
def _rows_of(tree: Any) -> int:
    return jax.tree.leaves(tree)[0].shape[0]


def _written_out(fn: Callable[[Any], Any], tree: Any, group: int) -> Any:
    """``fn`` over consecutive static slices of ``group`` rows (the last one shorter if need be), in order."""
    n = _rows_of(tree)
    for start in range(0, n, group):
        rows = slice(start, min(n, start + group))
        part = fn(jax.tree.map(lambda x, rows=rows: x[rows], tree))
        tree = jax.tree.map(lambda x, y, rows=rows: x.at[rows].set(y), tree, part)
    return tree


def map_groups(fn: Callable[[Any], Any], tree: Any, group: int | None, unrolled: int) -> Any:
    """``fn`` applied to consecutive slices of ``group`` rows of ``tree`` (its leaves share a leading axis), one
    slice after another, each result written back in place; ``fn`` keeps the tree's structure and shapes. With
    ``group`` None or not smaller than the batch, simply ``fn(tree)``. For work whose rows are independent (an
    env step), so the values are those of ``fn(tree)``.

    A batch of up to ``unrolled`` groups (:attr:`ExecutionPlan.unrolled_groups`) has them written out with
    static slices; a larger one runs blocks of ``unrolled`` groups in a ``fori_loop`` of dynamic slices and
    updates, then the rows left over written out. In place, not ``lax.map``, whose stacked output would hold the
    tree twice (and which cannot reshape the zero-size leaves of an MJX state's ``act``)."""
    n = _rows_of(tree)
    if group is None or group >= n:
        return fn(tree)
    if unrolled < 1:
        raise ValueError(f"unrolled={unrolled}: expected an integer >= 1")
    block = group * unrolled  # rows per loop iteration
    if n <= block:
        return _written_out(fn, tree, group)
    n_blocks = n // block

    def one(i, t):
        start = i * block
        part = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, start, block), t)
        done = _written_out(fn, part, group)
        return jax.tree.map(lambda x, y: jax.lax.dynamic_update_slice_in_dim(x, y, start, 0), t, done)

    tree = jax.lax.fori_loop(0, n_blocks, one, tree)
    head = n_blocks * block
    if head == n:
        return tree
    tail = _written_out(fn, jax.tree.map(lambda x: x[head:], tree), group)
    return jax.tree.map(lambda x, y: x.at[head:].set(y), tree, tail)


def step_batch(env: Env, states: EnvState, actions: jax.Array, params: Any, plan: ExecutionPlan) -> EnvState:
    """``env.step`` over a batch (the leading axis), as ``plan`` says: vmapped over all of it, or with
    ``plan.env_group`` set and smaller than the batch, vmapped over that many envs at a time (:func:`map_groups`),
    traced under ``plan.tracing()``. Each env's step does not depend on the others, so the values are the same
    (bit for bit in the tests and on an H100; XLA may round a last bit differently when it compiles the code
    around the step differently, as at optimisation level 0)."""
    batch = jax.vmap(lambda s, a: env.step(s, a, params))
    with plan.tracing():
        return map_groups(lambda sa: (batch(*sa), sa[1]), (states, actions), plan.env_group,
                          plan.unrolled_groups)[0]
