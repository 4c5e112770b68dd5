"""The sim layer (openai_ros' ``RobotGazeboEnv``): advance a MuJoCo model by one control step.

One control step is ``n_substeps = running_step / timestep`` physics steps, run as a ``lax.scan`` so the whole
thing is one compiled loop. The low-level controller of the robot (if any) runs on every substep, as an
on-board controller would; the "pause/unpause" of Gazebo has no equivalent because nothing runs between calls.

The MJX state between steps is :class:`MjxState` (time, ``qpos``, ``qvel``, ``act``, warm start), not the whole
``mjx.Data``: each step rebuilds the rest, so batches, resets and the training carry move only what matters.
MJX steps are traced under :func:`jaxrobo.physics.mjx_lean.lean` where the plan being traced wants it
(:func:`jaxrobo.physics.mjx_lean.wanted`): one stage of ``mjx.step`` in a form XLA compiles better, the same values bit
for bit.

Backends are small classes on :class:`Simulator`, which owns the substep loop (:meth:`Simulator.advance`):
:class:`MjxSim` (``mjx``: MuJoCo MJX, the maintained engine and the default) and :class:`BraxPipelineSim` (one of
Brax's pipelines, ``generalized``, ``positional``, ``spring``, built from the same MJCF) are the engines, in
:data:`ENGINES`. Brax's pipelines need the Euler integrator and approximate some dynamics (``spring`` most), so
prefer ``mjx`` unless you compare engines. Robots may add a hand-written backend on :class:`ClosedFormSim` (state:
:class:`JointState`), with every constant read from the same compiled model (the quadcopter's ``rigid``, the
cart-pole's ``analytic``).

Public surface: call :func:`load_model` (compile an MJCF file: the robot owns its path) and
:func:`make_simulator` (the one place a backend name is resolved and checked; :func:`backend_choices` gives a
robot's names for its task option); subclass :class:`ClosedFormSim` for a hand-written backend (implement
``physics_step``), or :class:`Simulator` for another engine. A robot with a batch kernel for its control step
passes it to ``advance`` (``kernel=``), which runs a vmapped step through it under ``fused="pallas"``
(:func:`through_kernel`). Tasks and robots read a simulator through ``init``,
``qpos``, ``qvel``, ``advance``, ``forward`` (MJX), and the attributes ``backend`` (its name), ``mj_model``,
``timestep``, ``running_step`` and ``n_substeps``. Everything named with a leading underscore is private. This
module imports nothing from ``envs`` or ``agents``.
"""
from __future__ import annotations

import abc
import contextlib
import dataclasses
import functools
import importlib
import io
import math
import operator
import os
import warnings
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxrobo.physics import fused, mjx_lean
from jaxrobo.core.struct import pytree_dataclass

Controller = Callable[[Any, jax.Array], jax.Array]
#: A control step over a batch of envs: ``(states, commands) -> states``, every leaf with a leading env axis; one
#: with the attribute ``takes_physics`` also takes ``(states, commands, physics)``, each env's drawn domain.
BatchedAdvance = Callable[..., Any]


@contextlib.contextmanager
def quiet_imports():
    """Silence the 'Failed to import warp' lines MJX prints and Brax's unmaintained-pipeline warning."""
    sink = io.StringIO()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*not actively being maintained.*")
        warnings.filterwarnings("ignore", message=".*warp.*")
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            yield


mjx = mjx_lean.mjx  # imported on first use (seconds, and noisy): listing ids or reading configs never pays for it


@pytree_dataclass
class JointState:
    """Generalized coordinates in MuJoCo's convention (``qpos``, ``qvel``): the whole state of a hand-written
    backend (:mod:`envs.quadcopter.rigid_body`, :mod:`envs.cartpole.dynamics`), whose step needs nothing else."""

    qpos: jax.Array
    qvel: jax.Array


@pytree_dataclass
class MjxState:
    """The part of ``mjx.Data`` one MJX step reads from the last: MuJoCo's integration state, less what stays
    constant here (``mocap_*``, ``eq_active``, applied forces: the model's defaults) or is set every substep
    (``ctrl``). Everything else in ``mjx.Data`` (poses, inertias, forces, constraint rows) is recomputed by
    each step, so carrying it between steps, resets and training chunks only moves memory: on an H100 the
    cart-pole's 1,364 bytes of ``mjx.Data`` per env against 28 here made raw MJX control steps 1.17x faster at
    262,144 envs and 1.48x at 1,048,576 (0.97x at 65,536; 1.02-1.05x on 2 CPU cores). :meth:`Simulator.forward`
    rebuilds the full ``mjx.Data`` when a task needs derived quantities (body poses, sensors)."""

    time: jax.Array
    qpos: jax.Array
    qvel: jax.Array
    act: jax.Array
    qacc_warmstart: jax.Array

    @classmethod
    def of(cls, data: Any) -> "MjxState":
        return cls(**{f.name: getattr(data, f.name) for f in dataclasses.fields(cls)})

    def fields(self) -> dict[str, jax.Array]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


#: Most physics steps one control step may take: a tiny ``timestep`` would otherwise overflow the substep loop's
#: int32 length (a traceback from inside a compiled step) or step for hours per control step.
MAX_SUBSTEPS = 100_000


def substeps_for(running_step: float, timestep: float) -> int:
    """How many physics steps make one control step; the two must divide evenly (to 1e-6), in at most
    :data:`MAX_SUBSTEPS` physics steps."""
    if running_step <= 0 or timestep <= 0:
        raise ValueError(f"running_step ({running_step}) and timestep ({timestep}) must be > 0")
    n = running_step / timestep
    if n > MAX_SUBSTEPS:
        raise ValueError(f"timestep={timestep} s: running_step={running_step} s would take {n:.4g} physics steps "
                         f"per control step; expected at most {MAX_SUBSTEPS:,} (timestep >= "
                         f"{running_step / MAX_SUBSTEPS:.3g} s)")
    if abs(n - round(n)) > 1e-6 * max(1.0, n) or round(n) < 1:
        raise ValueError(
            f"running_step={running_step} s is not a whole multiple of the physics timestep={timestep} s; "
            f"choose running_step as k * {timestep} for an integer k >= 1"
        )
    return int(round(n))


class Simulator(abc.ABC):
    """Base of every backend: a compiled model advanced one control step at a time; every method is pure and
    jit/vmap friendly. A backend implements :meth:`init`, :meth:`qpos`, :meth:`qvel` and :meth:`physics_step`
    (and :meth:`forward` if it can rebuild ``mjx.Data``); :meth:`advance`, the substep loop with the robot's
    controller on every substep, is shared. ``backend`` is the backend's name (``"mjx"``, ``"analytic"``...)."""

    #: The backend's name, as tasks' ``backend`` option spells it.
    backend: str = ""
    #: True for hand-written closed-form steps: a few fused arithmetic ops, cheap to unroll and compile.
    cheap_step: bool = False

    def __init__(self, mj_model: mujoco.MjModel, running_step: float | None = None):
        """``mj_model`` is the whole model (rendering reads it); one control step is ``running_step`` seconds
        (default: one physics step), a whole multiple of the model's timestep."""
        self.mj_model = mj_model
        self.timestep = float(mj_model.opt.timestep)
        self.running_step = self.timestep if running_step is None else float(running_step)
        self.n_substeps = substeps_for(self.running_step, self.timestep)

    # -- state ---------------------------------------------------------------------------------------------
    @abc.abstractmethod
    def init(self, qpos: jax.Array, qvel: jax.Array) -> Any:
        """The backend's state at the given generalized positions and velocities."""

    @abc.abstractmethod
    def qpos(self, state: Any) -> jax.Array:
        """The generalized positions of a state (MuJoCo's ``qpos`` order)."""

    @abc.abstractmethod
    def qvel(self, state: Any) -> jax.Array:
        """The generalized velocities of a state (MuJoCo's ``qvel`` order)."""

    def forward(self, state: Any) -> Any:
        """The full ``mjx.Data`` of a state (MJX only: see :meth:`MjxSim.forward`)."""
        raise ValueError(f"forward() rebuilds mjx.Data; backend={self.backend!r} keeps its own pipeline state")

    # -- dynamics ------------------------------------------------------------------------------------------
    @abc.abstractmethod
    def physics_step(self, state: Any, ctrl: jax.Array) -> Any:
        """One physics step of ``timestep`` seconds with actuator controls ``ctrl``."""

    def advance(self, state: Any, command: jax.Array, controller: Controller | None = None,
                kernel: BatchedAdvance | None = None, physics: Any = None) -> Any:
        """One control step: ``n_substeps`` physics steps, the controller mapping (state, command) to ctrl each time.

        ``kernel``: the same control step over a batch (every leaf with a leading env axis), e.g. a robot's Pallas
        kernel (:attr:`jaxrobo.task.robot.Robot.advance_kernel`). Traced under ``ExecutionPlan(fused="pallas")``
        (:func:`jaxrobo.physics.fused.physics_kernels`), a vmapped ``advance`` calls it once on the whole batch
        (:func:`through_kernel`); otherwise it is not used.

        ``physics``: one env's physical parameters where they differ from the model's (domain randomisation: the
        backend's own form, e.g. :meth:`MjxSim.physics_step`'s model and data fields), passed to every
        ``physics_step``, and to a kernel that takes them (its attribute ``takes_physics``: ``kernel(state,
        command, physics)`` on the batch); a kernel that does not is then never used."""
        if kernel is not None and fused.physics_kernels() and (
                physics is None or getattr(kernel, "takes_physics", False)):
            return through_kernel(kernel, state, command, physics)

        def substep(s, _):
            ctrl = command if controller is None else controller(s, command)
            if physics is None:
                return self.physics_step(s, ctrl), None
            return self.physics_step(s, ctrl, physics), None

        if self.n_substeps == 1:
            return substep(state, None)[0]
        # Unrolling a short substep loop lets XLA fuse across substeps and saves a loop per control step. For
        # MJX on a CPU it only multiplies compile time; a closed-form backend (``cheap_step``) compiles in a
        # moment either way, so it is unrolled everywhere.
        short = self.n_substeps <= 8
        unroll = self.n_substeps if short and (self.cheap_step or jax.default_backend() == "gpu") else 1
        if self.cheap_step and fused.unroll_all_substeps():
            # The fused plan: every substep written out, so XLA fuses across them instead of keeping a loop.
            unroll = True
        return jax.lax.scan(substep, state, None, length=self.n_substeps, unroll=unroll)[0]


def _on_batch(kernel: Callable[[Any, Any], Any], rows: Any, shared: Any, per_row: bool) -> Any:
    """``kernel(rows, shared)`` on a batch (``shared`` with a leading row axis where ``per_row``); vmapped again (a
    sweep over configurations around the env batch), it flattens the new axis into the batch and still makes one
    call (``shared`` then becomes per row where it is batched)."""

    @jax.custom_batching.custom_vmap
    def batch(rows: Any, shared: Any) -> Any:
        return kernel(rows, shared)

    @batch.def_vmap
    def batch_of_batches(axis_size: int, in_batched: list, rows: Any, shared: Any) -> tuple[Any, Any]:
        def full(x: jax.Array, batched: bool) -> jax.Array:
            return x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)

        def merged(x: jax.Array, batched: bool) -> jax.Array:
            x = full(x, batched)
            return x.reshape((axis_size * x.shape[1],) + x.shape[2:])

        n = jax.tree.leaves(jax.tree.map(lambda x, b: x.shape[1 if b else 0], rows, in_batched[0]))[0]

        def one_per_row(x: jax.Array, batched: bool) -> jax.Array:  # -> [axis * n, ...]
            if per_row:  # already one per row: [axis, n, ...]
                return merged(x, batched)
            x = full(x, batched)  # one per configuration: [axis, ...]
            return jnp.broadcast_to(x[:, None], (axis_size, n) + x.shape[1:]).reshape((axis_size * n,) + x.shape[1:])

        per = per_row or any(jax.tree.leaves(in_batched[1]))
        if per:
            shared = jax.tree.map(one_per_row, shared, in_batched[1])
        out = _on_batch(kernel, jax.tree.map(merged, rows, in_batched[0]), shared, per)
        out = jax.tree.map(lambda x: x.reshape((axis_size, -1) + x.shape[1:]), out)
        return out, jax.tree.map(lambda _: True, out)

    return batch(rows, shared)


def through_batch(kernel: Callable[[Any, Any], Any], rows: Any, shared: Any = ()) -> Any:
    """One env's ``rows`` (a pytree) computed by ``kernel(rows_batch, shared)``, a function of a batch: under
    ``vmap`` (an env batch, and any vmap around it) one call on the whole batch, instead of the kernel traced per
    env; unbatched, a batch of one. ``shared`` (e.g. a task's parameters) reaches the kernel as it is, or, where a
    vmap batches it (a sweep over them), with a leading axis of one value per row: the kernel tells the two apart
    by shape."""

    @jax.custom_batching.custom_vmap
    def one(rows: Any, shared: Any) -> Any:
        out = _on_batch(kernel, jax.tree.map(lambda x: x[None], rows), shared, False)
        return jax.tree.map(lambda x: x[0], out)

    @one.def_vmap
    def batched(axis_size: int, in_batched: list, rows: Any, shared: Any) -> tuple[Any, Any]:
        spread = lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + x.shape)  # noqa: E731
        per = any(jax.tree.leaves(in_batched[1]))
        out = _on_batch(kernel, jax.tree.map(spread, rows, in_batched[0]),
                        jax.tree.map(spread, shared, in_batched[1]) if per else shared, per)
        return out, jax.tree.map(lambda _: True, out)

    return one(rows, shared)


def through_kernel(kernel: BatchedAdvance, state: Any, command: jax.Array, physics: Any = None) -> Any:
    """One env's control step computed by ``kernel``, a function of a batch (:func:`through_batch`); ``physics``
    (one env's drawn domain, for a kernel that takes it) travels as rows beside the state."""
    rows = (state, command) if physics is None else (state, command, physics)
    return through_batch(lambda rows, _: kernel(*rows), rows)


def constraint_free(m: mujoco.MjModel) -> bool:
    """True when ``m`` can have no constraint rows: contacts disabled, no joint or tendon limits, no equality
    constraints, no friction loss (so MJX's constraint solver never runs)."""
    contact = not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return not (contact or m.jnt_limited.any() or m.neq or m.dof_frictionloss.any()
                or (m.ntendon and m.tendon_limited.any()))


@pytree_dataclass
class MjxEdit:
    """One env's changes to an MJX model (``model``: ``mjx.Model`` field name -> value) and to the data fields
    the model leaves at their defaults (``data``: e.g. ``xfrc_applied``), for :meth:`MjxSim.physics_step`."""

    model: dict
    data: dict


class MjxSim(Simulator):
    """MuJoCo MJX (backend ``mjx``, the maintained engine). Its state is an :class:`MjxState`."""

    backend = "mjx"

    def __init__(self, mj_model: mujoco.MjModel, running_step: float | None = None,
                 physics_model: mujoco.MjModel | Callable[[], mujoco.MjModel] | None = None):
        """MJX integrates ``physics_model`` if given (or returned by it, when a function): the same model loaded
        with ``load_model(..., physics_only=True)``, whose dynamics must be the same as ``mj_model``'s."""
        super().__init__(mj_model, running_step)
        physics = physics_model() if callable(physics_model) else physics_model
        if physics is None:
            physics = mj_model
        elif physics is not mj_model:
            check_same_dynamics(mj_model, physics)
        # This process's first device: MJX's default is jax.devices()[0], which in a multi-host run belongs to
        # process 0, and another process cannot close over arrays it cannot address.
        device = jax.local_devices()[0]
        self.model = mjx.put_model(physics, device=device)
        self._data0 = mjx.put_data(physics, mujoco.MjData(physics), device=device)
        self.constraint_free = constraint_free(physics)
        self._jitted_steps: dict[bool, Callable] = {}

    def init(self, qpos: jax.Array, qvel: jax.Array) -> MjxState:
        return MjxState.of(self._data0).replace(qpos=jnp.asarray(qpos, jnp.float32),
                                                 qvel=jnp.asarray(qvel, jnp.float32))

    def qpos(self, state: MjxState) -> jax.Array:
        return state.qpos

    def qvel(self, state: MjxState) -> jax.Array:
        return state.qvel

    def forward(self, state: MjxState) -> Any:
        """The full ``mjx.Data`` of an MJX state, with every derived quantity (body poses, velocities, sensors)
        computed by ``mjx.forward`` on the integrated model (``physics_only``: no visual geoms): for tasks that
        read more than ``qpos``/``qvel``."""
        with mjx_lean.lean(mjx_lean.wanted()):
            return mjx.forward(self.model, self._data0.replace(**state.fields()))

    def physics_step(self, state: MjxState, ctrl: jax.Array, physics: MjxEdit | None = None) -> MjxState:
        """One MJX step; ``physics`` (domain randomisation) replaces fields of the model and of the data (applied
        forces) for this env: under ``vmap`` a batched model, as MuJoCo Playground's randomisers build one."""
        return self._jitted_step(mjx_lean.wanted())(state, ctrl, physics)

    # The step is jitted on its own so that JAX traces MJX's Python once per process (and lean choice): the
    # training chunk, the greedy flights' programs and a sweep's all call it, and each traced it again (ArmReach-v0
    # on 2 CPU cores: the flight's trace 2.9 s -> 1.5 s). XLA inlines the call: the programs and their numbers are
    # the ones traced inline (the fingerprints are the same).
    def _jitted_step(self, lean: bool) -> Callable[[MjxState, jax.Array, MjxEdit | None], MjxState]:
        jitted = self._jitted_steps.get(lean)
        if jitted is None:
            jitted = self._jitted_steps.setdefault(lean, jax.jit(functools.partial(self._mjx_step, lean)))
        return jitted

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_jitted_steps": {}}  # jitted functions do not pickle; made again on first use

    def _mjx_step(self, lean: bool, state: MjxState, ctrl: jax.Array, physics: MjxEdit | None) -> MjxState:
        model, data0 = self.model, self._data0
        if physics is not None:
            model, data0 = model.replace(**physics.model), data0.replace(**physics.data)
        with mjx_lean.lean(lean):
            out = MjxState.of(mjx.step(model, data0.replace(ctrl=ctrl, **state.fields())))
        if self.constraint_free:
            # MJX keeps each step's accelerations as the constraint solver's next warm start. A model that can
            # have no constraint rows never runs the solver, so nothing reads it; carried, it holds float32
            # round-off amplified by stiff actuators (kp / inertia), which differs between a jitted and a
            # vmapped compile of the same step and would make a state comparison fail on a value nothing uses.
            out = out.replace(qacc_warmstart=jnp.zeros_like(out.qacc_warmstart))
        return out


class BraxPipelineSim(Simulator):
    """One of Brax's pipelines built from the same MJCF; subclasses name it (:class:`GeneralizedSim`,
    :class:`PositionalSim`, :class:`SpringSim`). They need the Euler integrator and approximate some dynamics
    (``spring`` most). The state is the pipeline's own (``q``, ``qd``)."""

    def __init__(self, mj_model: mujoco.MjModel, running_step: float | None = None, physics_model: Any = None):
        """Brax's loader reads ``mj_model`` whole (it needs the geoms): ``physics_model`` is for MJX only."""
        super().__init__(mj_model, running_step)
        if mj_model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
            raise ValueError(f"backend={self.backend!r} needs the Euler integrator in the MJCF <option>")
        with quiet_imports():
            from brax.io import mjcf

            self.model = mjcf.load_model(mj_model)
            self._pipeline = importlib.import_module(f"brax.{self.backend}.pipeline")

    def init(self, qpos: jax.Array, qvel: jax.Array) -> Any:
        with quiet_imports():
            return self._pipeline.init(self.model, qpos, qvel)

    def qpos(self, state: Any) -> jax.Array:
        return state.q

    def qvel(self, state: Any) -> jax.Array:
        return state.qd

    def physics_step(self, state: Any, ctrl: jax.Array) -> Any:
        return self._pipeline.step(self.model, state, ctrl)


class GeneralizedSim(BraxPipelineSim):
    backend = "generalized"


class PositionalSim(BraxPipelineSim):
    backend = "positional"


class SpringSim(BraxPipelineSim):
    backend = "spring"


class ClosedFormSim(Simulator):
    """Base of a hand-written backend: the state is a :class:`JointState` and ``physics_step`` is the model's
    equations of motion, with its constants read from ``mj_model`` by the subclass (so the MJCF stays the single
    source of truth). ``advance`` and the controller-every-substep contract are the base class's. A robot offers
    it by name through ``make_simulator(..., closed_form={name: factory})``."""

    cheap_step = True

    def __init__(self, mj_model: mujoco.MjModel, backend: str, running_step: float | None = None):
        super().__init__(mj_model, running_step)
        self.backend = backend
        self.model = None

    def init(self, qpos: jax.Array, qvel: jax.Array) -> JointState:
        return JointState(jnp.asarray(qpos, jnp.float32), jnp.asarray(qvel, jnp.float32))

    def qpos(self, state: Any) -> jax.Array:
        return state.qpos

    def qvel(self, state: Any) -> jax.Array:
        return state.qvel


#: The engines that step any MJCF, by backend name (MJX first: the default).
ENGINES: dict[str, type[Simulator]] = {cls.backend: cls for cls in (MjxSim, GeneralizedSim, PositionalSim, SpringSim)}
#: Their names, in that order.
BACKENDS = tuple(ENGINES)

#: A robot's hand-written backend, built from the whole model and the control step.
ClosedFormFactory = Callable[[mujoco.MjModel, Any], ClosedFormSim]


def backend_choices(closed_form: Mapping[str, ClosedFormFactory] | None = None,
                    engines: Sequence[str] = BACKENDS) -> tuple[str, ...]:
    """The backend names a robot accepts: the ``engines`` it runs on, then its closed forms (the order of a
    task option's ``choices``)."""
    unknown = [name for name in engines if name not in ENGINES]
    if unknown:
        raise ValueError(f"engines={unknown}: allowed values are {', '.join(ENGINES)}")
    return tuple(engines) + tuple(closed_form or ())


def make_simulator(mj_model: mujoco.MjModel, backend: str = "mjx", running_step: float | None = None,
                   physics_model: mujoco.MjModel | Callable[[], mujoco.MjModel] | None = None, *,
                   closed_form: Mapping[str, ClosedFormFactory] | None = None,
                   engines: Sequence[str] = BACKENDS) -> Simulator:
    """The simulator of ``mj_model`` for the backend named ``backend``: one of ``engines`` (by default every
    engine in :data:`ENGINES`) or one of the robot's ``closed_form`` backends, each called as
    ``factory(mj_model, running_step)``. The one place a backend name is checked.

    ``physics_model`` (a model or a function returning one, called only when needed) is what MJX integrates:
    the same MJCF loaded with ``physics_only=True``; Brax's pipelines and closed forms read ``mj_model``."""
    choices = backend_choices(closed_form, engines)
    if backend not in choices:
        raise ValueError(f"backend={backend!r}: allowed values are {', '.join(choices)}")
    if closed_form is not None and backend in closed_form:
        return closed_form[backend](mj_model, running_step)
    return ENGINES[backend](mj_model, running_step, physics_model=physics_model)


def check_same_dynamics(model: mujoco.MjModel, physics: mujoco.MjModel) -> None:
    """Refuse a physics model whose dynamics could differ from ``model``'s (a ``physics_only`` load of another
    file or with other options): same sizes, step, integrator, joints, actuators, masses and inertias."""
    fields = ("nq", "nv", "nu", "nbody", "njnt", "opt.timestep", "opt.integrator", "opt.gravity", "jnt_type",
              "body_mass", "body_inertia", "body_ipos", "body_iquat", "actuator_trntype", "actuator_gear",
              "actuator_gainprm", "actuator_biasprm", "dof_damping", "dof_armature")
    for name in fields:
        a, b = (np.asarray(operator.attrgetter(name)(m)) for m in (model, physics))
        if a.shape != b.shape or not np.array_equal(a, b):
            raise ValueError(f"physics_model differs from mj_model in {name}; load both from the same MJCF and "
                             f"options (physics_model with load_model(..., physics_only=True))")


def load_model(xml_path: str, keep_actuators: tuple[str, ...] | None = None, timestep: float | None = None,
               edit: Callable[[Any], None] | None = None, physics_only: bool = False) -> mujoco.MjModel:
    """Compile an MJCF file, keeping only the named actuators and optionally overriding the physics timestep.

    ``physics_only``: leave out what only a renderer uses - visual geoms (``contype = conaffinity = 0``), lights
    and cameras no sensor reads. MuJoCo still takes masses and inertias from the dropped geoms, so the dynamics
    are the same bit for bit, but MJX no longer computes their poses every step (the cart-pole without its four
    visual geoms, camera and light: 1.3-1.5x the MJX control steps per second on 2 CPU cores, +2-5 % on an H100).
    """
    spec = mujoco.MjSpec.from_file(xml_path)
    if physics_only:
        spec.compiler.discardvisual = True
        seen_by_sensors = {s.objname for s in spec.sensors if s.objtype == mujoco.mjtObj.mjOBJ_CAMERA}
        for item in list(spec.lights) + [c for c in spec.cameras if c.name not in seen_by_sensors]:
            spec.delete(item)
    if keep_actuators is not None:
        names = [a.name for a in spec.actuators]
        missing = set(keep_actuators) - set(names)
        if missing:
            raise ValueError(f"{os.path.basename(xml_path)} has no actuator {sorted(missing)}; it has {names}")
        for act in list(spec.actuators):
            if act.name not in keep_actuators:
                spec.delete(act)
    if timestep is not None:
        spec.option.timestep = timestep
    if edit is not None:
        edit(spec)
    model = spec.compile()
    if not math.isfinite(model.opt.timestep) or model.opt.timestep <= 0:
        raise ValueError(f"bad timestep in {xml_path}")
    return model
