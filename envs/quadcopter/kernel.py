"""The rigid quadcopter's control step as one Pallas kernel: every substep of the on-board controller and the
rigid-body physics for a block of envs, each env's state in registers from the first substep to the last.

Why: on the XLA path a control step of the Goto tasks is 30 substeps of :meth:`envs.quadcopter.robot.Quadcopter.
controller` + :meth:`envs.quadcopter.rigid_body.RigidBodySim.physics_step`, which XLA splits into several batch-wide
kernels, so the whole env state goes through memory many times per control step. Here each env reads its 13 state floats
and 4 command floats once and writes 13, whatever the number of substeps.

What it computes: the XLA step's own equations, :func:`envs.quadcopter.dynamics.controller` and
:func:`envs.quadcopter.dynamics.physics_step`, which are written per coordinate so that the kernel runs them on
``[block]`` vectors (Triton has no slice, so a state is a list of 7 + 6 vectors rather than one array), with the
robot's and the simulator's own constants (:func:`constants_of`). Op by op a control step here is the XLA
step's bit for bit (``tests/test_quadcopter_kernel.py``); compiled, the two programs are fused differently (on
a CPU XLA contracts a multiply and an add within a fusion into one FMA; on a GPU Triton compiles the kernel and
takes ``atan2``/``sin``/``cos`` from libdevice), so they agree to float32 round-off.

Domain randomisation: a randomised task's step hands each env's drawn physics (mass and motor-gain factors, the
wind's force: :meth:`envs.quadcopter.robot.Quadcopter.sim_physics`) to the kernel as per-env inputs
(:data:`PHYSICS`), which :func:`envs.quadcopter.dynamics.physics_step` takes as the XLA step does; without them
the kernel is the nominal program it always was.

How it is used: :func:`make_advance` builds the batch function the robot offers as ``advance_kernel``
(:class:`jaxrobo.task.robot.Robot`); under ``ExecutionPlan(fused="pallas")``
:meth:`jaxrobo.physics.sim.Simulator.advance` runs a vmapped control step through it, one kernel call for the whole
batch. On a CPU it runs interpreted (the tests' oracle checks), on a GPU through Triton.

Public surface: :func:`make_advance`, :func:`control_step` (the per-coordinate step, for any array shape) with
its :class:`Constants` (:func:`constants_of`), :data:`BLOCK`.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp

from envs.quadcopter.dynamics import BodyConstants, ControllerConstants, controller, physics_step
from jaxrobo.api import JointState

#: Envs per Pallas program (a power of two, as Triton's blocks are). On an H100 one env per thread ran fastest
#: (blocks of 32-128 envs at 1-4 warps alike; two envs per thread 0.67-0.95x), and 128 fills more SMs than 256
#: at small batches (1.15x at 1,024 envs, 0.97x at 65,536, 1.0x at 1 M; docs/benchmarks.md, "Pallas: quadcopter").
BLOCK = 128


@dataclasses.dataclass(frozen=True)
class Constants:
    """Every number the control step needs (host floats; baked into the kernel)."""

    n_substeps: int
    controller: ControllerConstants
    body: BodyConstants


def constants_of(robot: Any) -> Constants:
    """The constants of a :class:`~envs.quadcopter.robot.Quadcopter` on the ``rigid`` backend: its controller's and
    its simulator's, the very ones its XLA path computes with."""
    return Constants(int(robot.sim.n_substeps), robot.control, robot.sim.constants)


def control_step(c: Constants, q: Sequence[Any], v: Sequence[Any], cmd: Sequence[Any],
                 physics: dict | None = None) -> tuple[list, list]:
    """One control step (``c.n_substeps`` substeps of controller + physics) on per-coordinate arrays of any
    shape: 7 position coordinates, 6 velocity coordinates and 4 command values. ``physics``: each env's drawn
    domain (domain randomisation; :func:`envs.quadcopter.dynamics.physics_step`'s argument, ``wind`` as a list of
    3 coordinates), None for the nominal airframe; the controller keeps the nominal values, as on the XLA path."""

    def substep(_, carry):
        q, v = list(carry[:7]), list(carry[7:])
        q, v = physics_step(jnp, c.body, q, v, controller(jnp, c.controller, q, v, cmd), physics)
        return tuple(q) + tuple(v)

    out = jax.lax.fori_loop(0, c.n_substeps, substep, tuple(q) + tuple(v))
    return list(out[:7]), list(out[7:])


#: The per-env inputs of a randomised control step (domain randomisation), with their values per env: the
#: physics of :meth:`envs.quadcopter.robot.Quadcopter.sim_physics` (factors on mass and motor gain, the wind's
#: world-frame force).
PHYSICS = (("mass", 1), ("motor_gain", 1), ("wind", 3))


def _kernel(c: Constants, n: int, block: int, randomised: bool = False) -> Callable:
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    def kernel(qpos_ref, qvel_ref, cmd_ref, *refs):
        domain_refs, (qpos_out, qvel_out) = refs[:-2], refs[-2:]
        env = pl.program_id(0) * block + jax.lax.iota(jnp.int32, block)
        mask = env < n
        # Each env's row read and written word by word: the rows of a block are contiguous, so the words of
        # a row come from the same cache lines.
        q = [plgpu.load(qpos_ref.at[env * 7 + j], mask=mask, other=0.0) for j in range(7)]
        v = [plgpu.load(qvel_ref.at[env * 6 + j], mask=mask, other=0.0) for j in range(6)]
        cmd = [plgpu.load(cmd_ref.at[env * 4 + j], mask=mask, other=0.0) for j in range(4)]
        physics = None
        if randomised:  # each env's drawn physics, read once per control step (masked lanes: 1, harmless)
            loaded = {name: [plgpu.load(ref.at[env * width + j], mask=mask, other=1.0) for j in range(width)]
                      for (name, width), ref in zip(PHYSICS, domain_refs)}
            physics = {name: values if len(values) > 1 else values[0] for name, values in loaded.items()}
        q, v = control_step(c, q, v, cmd, physics)
        for j in range(7):
            plgpu.store(qpos_out.at[env * 7 + j], q[j], mask=mask)
        for j in range(6):
            plgpu.store(qvel_out.at[env * 6 + j], v[j], mask=mask)

    return kernel


def make_advance(robot: Any, block: int | None = None, num_warps: int | None = None,
                 interpret: bool | None = None) -> Callable[..., JointState]:
    """The robot's control step over a batch: ``(JointState [n], command [n, 4], physics=None) -> JointState
    [n]``, one Pallas call. ``physics``: each env's drawn domain (domain randomisation), the dict
    :meth:`envs.quadcopter.robot.Quadcopter.sim_physics` gives with a leading env axis (:data:`PHYSICS`); None
    (the nominal airframe) traces the kernel without those inputs, the program it always was.
    ``block``/``num_warps``: envs and warps per program (defaults :data:`BLOCK` and one thread per env);
    ``interpret``: run the kernel interpreted (default: unless JAX's default backend is a GPU)."""
    c = constants_of(robot)

    def advance(state: JointState, command: jax.Array, physics: dict | None = None) -> JointState:
        from jax.experimental import pallas as pl
        from jax.experimental.pallas import triton as plgpu

        n = state.qpos.shape[0]
        if n == 0:
            return state
        size = BLOCK if block is None else block
        size = min(size, max(1, 1 << (n - 1).bit_length()))  # a batch smaller than a block: one short program
        warps = max(1, min(8, size // 32)) if num_warps is None else num_warps  # default: one thread per env
        run_interpreted = jax.default_backend() != "gpu" if interpret is None else interpret
        params = None if run_interpreted else plgpu.CompilerParams(num_warps=warps, num_stages=1)
        whole = pl.BlockSpec(memory_space=pl.ANY)
        flat = lambda x: jnp.asarray(x, jnp.float32).reshape(-1)  # noqa: E731
        domain = [] if physics is None else [flat(physics[name]) for name, _ in PHYSICS]
        qpos, qvel = pl.pallas_call(
            _kernel(c, n, size, physics is not None), grid=(-(-n // size),), in_specs=[whole] * (3 + len(domain)),
            out_specs=[whole] * 2,
            out_shape=[jax.ShapeDtypeStruct((n * 7,), jnp.float32), jax.ShapeDtypeStruct((n * 6,), jnp.float32)],
            interpret=run_interpreted, compiler_params=params, name="quadcopter_control_step",
        )(flat(state.qpos), flat(state.qvel), flat(command), *domain)
        return JointState(qpos.reshape(n, 7), qvel.reshape(n, 6))

    #: It takes each env's drawn physics (:meth:`jaxrobo.physics.sim.Simulator.advance` hands them to it).
    advance.takes_physics = True
    return advance
