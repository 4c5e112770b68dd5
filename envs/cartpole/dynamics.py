"""Closed-form dynamics of the cart-pole: the cart-pole's fast backend (``analytic``).

A cart on a slider carrying a pole on a hinge has a 2×2 mass matrix and two bias forces that fit on one line
each, so a whole MuJoCo step reduces to a dozen multiply-adds. :class:`CartPoleSim` evaluates them with every
constant read from the compiled :class:`mujoco.MjModel` (cart and pole masses, the pole's centre of mass and
inertia, joint armature, gravity, timestep, each actuator's gain, bias, gear and limits), so the MJCF stays
the single source of truth, and refuses a model it cannot reproduce (limits, damping, contacts, activation
dynamics, a tilted axis). It mirrors MuJoCo's semi-implicit Euler step, and agrees with native MuJoCo to
float64 round-off (``tests/test_cartpole_physics.py``).

Why it exists: MJX steps the cart-pole through its general articulated-body pipeline (tree scans, a
Cholesky factorisation, dozens of small kernels), which costs ~1 µs per physics step per env on 2 CPU
cores and keeps a GPU latency-bound at small batches. The closed form is one fused kernel: use ``mjx`` to
check a result against the maintained engine, ``analytic`` when the cart-pole is only the test bed.

Coordinates (MuJoCo's, in the order of ``qpos``): ``x`` (m) the cart on the slider, ``θ`` (rad) the pole angle
about the hinge axis +y, 0 upright, positive tipping the pole's top towards +x. With the pole's centre of
mass at distance ``l`` above the hinge, its inertia ``I`` about the hinge-parallel axis through that centre::

    M(θ) = [[m_c + m_p + a_x,  m_p l cos θ        ],
            [m_p l cos θ,      m_p l² + I + a_θ   ]]
    M q̈ = [F_x + m_p l sin θ θ̇²,  τ_θ + m_p g l sin θ]

with ``a`` the joint armatures and ``F_x``, ``τ_θ`` the actuator forces on the two joints.

Written once: :func:`accelerations` (the actuator forces and the 2×2 solve) and :func:`euler` (the integration)
are the equations, on scalars or arrays of any common shape. :meth:`CartPoleSim.physics_step`, the XLA path, calls
them on one env's coordinates and integrates the stacked ``[x, θ]`` vectors; :meth:`CartPoleSim.coordinate_step`
calls them on the four coordinates held apart, which is what the Pallas chunk kernel
(:mod:`envs.cartpole.kernel`) runs on its ``[block]`` vectors, reaching it through the env's simulator and
passing its own ``sin``/``cos`` on a GPU. Op by op the two forms give the same bits
(``tests/test_cartpole_physics.py``).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxrobo.api import ClosedFormSim, JointState, actuators


@dataclasses.dataclass(frozen=True)
class CartPoleConstants:
    """Constants of the cart-pole read from a compiled model (host numpy; baked into the trace).
    Coordinates are ``(x, θ)`` = ``qpos[0], qpos[1]``."""

    total_mass: float  # m_c + m_p + armature of the slider (kg)
    pole_mass_length: float  # m_p l (kg m)
    pole_inertia: float  # m_p l² + I + armature of the hinge (kg m²)
    gravity: float  # g > 0, pointing -z (m/s²)
    transmission: np.ndarray  # [2, n_act] gear of actuator j on coordinate i (one-hot rows)
    gain: np.ndarray  # [n_act] force per unit control
    bias: np.ndarray  # [3, n_act] force = gain ctrl + b0 + b1 length + b2 velocity
    ctrl_low: np.ndarray
    ctrl_high: np.ndarray
    force_low: np.ndarray
    force_high: np.ndarray
    # The parts the three sums above are made of, for domain randomisation (:func:`randomised`).
    cart_mass: float = 0.0  # m_c (kg)
    pole_mass: float = 0.0  # m_p (kg)
    pole_length: float = 0.0  # l: hinge to the pole's centre of mass (m)
    pole_inertia_com: float = 0.0  # I about the centre of mass (kg m²)
    armature_x: float = 0.0
    armature_th: float = 0.0
    # Two products of the above the equations use, computed once on the host (float64, as the trace always did).
    mass_inertia: float = 0.0  # total_mass * pole_inertia
    weight_arm: float = 0.0  # pole_mass_length * gravity

    @functools.cached_property
    def actuators(self) -> tuple:
        """Per actuator, in Python floats, what :func:`accelerations` reads
        (:func:`jaxrobo.physics.actuators.actuator_rows`)."""
        return actuators.actuator_rows(self.transmission, self.gain, self.bias, self.ctrl_low, self.ctrl_high,
                                       self.force_low, self.force_high)


def _refuse(condition: bool, why: str) -> None:
    if condition:
        raise ValueError(f"the analytic cart-pole backend cannot model this MJCF: {why}; use backend='mjx'")


def constants_from_model(mj_model: mujoco.MjModel, cart_joint: str, pole_joint: str) -> CartPoleConstants:
    """Read the cart-pole's constants from ``mj_model``; refuse anything the closed form does not describe."""
    m = mj_model
    jid = {name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name) for name in (cart_joint, pole_joint)}
    _refuse(min(jid.values()) < 0, f"joints {cart_joint!r} and {pole_joint!r} must both exist")
    slide, hinge = jid[cart_joint], jid[pole_joint]
    _refuse(m.njnt != 2 or m.nbody != 3, "exactly world + cart + pole bodies, one joint each")
    _refuse(m.jnt_type[slide] != mujoco.mjtJoint.mjJNT_SLIDE or m.jnt_type[hinge] != mujoco.mjtJoint.mjJNT_HINGE,
            f"{cart_joint!r} must be a slide and {pole_joint!r} a hinge")
    cart, pole = int(m.jnt_bodyid[slide]), int(m.jnt_bodyid[hinge])
    _refuse(m.body_parentid[cart] != 0 or m.body_parentid[pole] != cart,
            "the pole's body must be a child of the cart's")
    for b in (cart, pole):
        _refuse(np.abs(m.body_quat[b] - [1, 0, 0, 0]).max() > 1e-9, "body frames must be aligned with the world")
    _refuse(np.abs(m.jnt_axis[slide] - [1, 0, 0]).max() > 1e-9, "the slide axis must be +x")
    _refuse(np.abs(m.jnt_axis[hinge] - [0, 1, 0]).max() > 1e-9, "the hinge axis must be +y")
    _refuse(np.abs(m.jnt_pos[hinge]).max() > 1e-9, "the hinge must sit at the pole body's origin")
    _refuse(bool(m.jnt_limited.any()), "joint limits are constraints")
    _refuse(bool(np.any(m.dof_damping) or np.any(m.dof_frictionloss) or np.any(m.jnt_stiffness)),
            "joint damping, friction loss or stiffness")
    _refuse(not (m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT), "contacts must be disabled")
    _refuse(m.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER, "the closed form mirrors the Euler integrator")
    _refuse(bool(m.opt.density or m.opt.viscosity), "fluid forces")
    _refuse(np.abs(m.opt.gravity[:2]).max() > 0, "gravity must point along -z")
    com = m.body_ipos[pole]
    _refuse(abs(com[0]) > 1e-9, "the pole's centre of mass must lie on its z axis")
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, m.body_iquat[pole])
    rot = rot.reshape(3, 3)
    inertia_y = float((rot @ np.diag(m.body_inertia[pole]) @ rot.T)[1, 1])
    mass_c, mass_p, length = float(m.body_mass[cart]), float(m.body_mass[pole]), float(com[2])
    arm = m.dof_armature
    _refuse((m.jnt_qposadr[slide], m.jnt_qposadr[hinge], m.jnt_dofadr[slide], m.jnt_dofadr[hinge]) != (0, 1, 0, 1),
            "the cart's coordinate must come first in qpos and qvel")

    actuated = actuators.joint_actuators(m, _refuse)
    total_mass = mass_c + mass_p + float(arm[m.jnt_dofadr[slide]])
    pole_mass_length = mass_p * length
    pole_inertia = mass_p * length**2 + inertia_y + float(arm[m.jnt_dofadr[hinge]])
    gravity = float(-m.opt.gravity[2])
    return CartPoleConstants(
        total_mass=total_mass, pole_mass_length=pole_mass_length, pole_inertia=pole_inertia, gravity=gravity,
        **actuated,
        cart_mass=mass_c, pole_mass=mass_p, pole_length=length, pole_inertia_com=inertia_y,
        armature_x=float(arm[m.jnt_dofadr[slide]]), armature_th=float(arm[m.jnt_dofadr[hinge]]),
        mass_inertia=total_mass * pole_inertia, weight_arm=pole_mass_length * gravity,
    )


def randomised(c: CartPoleConstants, physics: dict) -> CartPoleConstants:
    """``c`` for one env's drawn factors (domain randomisation): ``cart_mass``, ``pole_mass`` and ``pole_length``
    (the pole scaled as a rod: its inertia about the centre of mass by mass x length²); the sums and products
    traced. Each is written as the nominal value plus a change that is exactly 0 at factors of 1 (or the nominal
    value times a factor product), so that a randomised step at the nominal values computes the nominal step's
    operations on the same values: a zero-width range gives the nominal bits, op by op."""
    f_cart, f_mass, f_length = physics["cart_mass"], physics["pole_mass"], physics["pole_length"]
    f_ml = f_mass * f_length  # on m_p l
    f_inertia = f_ml * f_length  # on m_p l² + I (a rod)
    total = c.total_mass + c.cart_mass * (f_cart - 1.0) + c.pole_mass * (f_mass - 1.0)
    inertia = c.pole_inertia + (c.pole_inertia - c.armature_th) * (f_inertia - 1.0)
    return dataclasses.replace(
        c, total_mass=total, pole_mass_length=c.pole_mass_length * f_ml, pole_inertia=inertia,
        mass_inertia=c.mass_inertia + (total - c.total_mass) * inertia + c.total_mass * (inertia - c.pole_inertia),
        weight_arm=c.weight_arm * f_ml)


class CartPoleSim(ClosedFormSim):
    """A :class:`~jaxrobo.physics.sim.ClosedFormSim` over the closed-form cart-pole (backend ``analytic``)."""

    def __init__(self, mj_model: mujoco.MjModel, cart_joint: str, pole_joint: str,
                 running_step: float | None = None):
        self.constants = constants_from_model(mj_model, cart_joint, pole_joint)
        super().__init__(mj_model, "analytic", running_step)

    def physics_step(self, state: JointState, ctrl: jax.Array, physics: dict | None = None) -> JointState:
        """One step; ``physics``: one env's factors (domain randomisation, :func:`randomised`)."""
        c = self.constants if physics is None else randomised(self.constants, physics)
        q, v = state.qpos, state.qvel
        acc_x, acc_th, inv_det = accelerations(c, q[0], q[1], v[0], v[1], ctrl)
        # Whole-vector updates: on a CPU they vectorise better than per-coordinate ones over the batch.
        q, v = euler(q, v, jnp.stack([acc_x, acc_th]), inv_det, self.timestep)
        return JointState(q, v)

    def coordinate_step(self, x: jax.Array, th: jax.Array, xd: jax.Array, thd: jax.Array, ctrl: Any,
                        sincos: SinCos = None, physics: dict | None = None, xp: Any = jnp
                        ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
        """:meth:`physics_step` on the four coordinates ``(x, θ, ẋ, θ̇)`` held apart (scalars or same-shape
        arrays, as a Pallas kernel holds them: it has no slice), with ``ctrl`` one value per actuator,
        ``sincos`` the kernel's own ``θ -> (sin θ, cos θ)`` (default ``jnp.sin``/``jnp.cos``) and ``physics``
        each env's drawn factors (domain randomisation, :func:`randomised`; same-shape arrays). The same
        functions, hence the same operations on each element, as :meth:`physics_step`. ``xp``: the array module
        (``jax.numpy``; :data:`jaxrobo.core.scalar.FLOATS` for one env on the host in Python floats)."""
        c = self.constants if physics is None else randomised(self.constants, physics)
        acc_x, acc_th, inv_det = accelerations(c, x, th, xd, thd, ctrl, sincos, xp)
        x, xd = euler(x, xd, acc_x, inv_det, self.timestep)
        th, thd = euler(th, thd, acc_th, inv_det, self.timestep)
        return x, th, xd, thd


#: ``θ -> (sin θ, cos θ)``; None: ``jnp.sin``, ``jnp.cos``.
SinCos = Optional[Callable[[jax.Array], tuple[jax.Array, jax.Array]]]


def accelerations(c: CartPoleConstants, x: jax.Array, th: jax.Array, xd: jax.Array, thd: jax.Array, ctrl: Any,
                  sincos: SinCos = None, xp: Any = jnp) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The cart-pole's equations of motion, per coordinate: ``(a_x, a_θ, 1/det M)`` with ``q̈ = a / det M``.

    ``ctrl[j]`` is actuator j's control. Every argument may be a scalar or an array of any common shape
    (``[block]`` vectors in the Pallas kernel, one env's values under ``vmap``); ``sincos`` lets a kernel use its
    own ``sin``/``cos`` (default: those of ``xp``, the array module: ``jax.numpy``, or
    :data:`jaxrobo.core.scalar.FLOATS` for Python floats on the host). The division by the determinant is left to
    the caller so that :meth:`CartPoleSim.physics_step` scales both accelerations as one stacked vector (as it
    always has: the CPU's fixed-seed results stay bit for bit) while a kernel scales each coordinate."""
    generalized = actuators.generalized_forces(c.actuators, (x, th), (xd, thd), ctrl, xp)  # mj_fwdActuation
    # Dynamics: solve the 2×2 system M q̈ = rhs in closed form.
    sin, cos = (xp.sin(th), xp.cos(th)) if sincos is None else sincos(th)
    coupling = c.pole_mass_length * cos
    rhs_x = generalized[0] + c.pole_mass_length * sin * thd * thd
    rhs_th = generalized[1] + c.weight_arm * sin
    inv_det = 1.0 / (c.mass_inertia - coupling * coupling)
    return c.pole_inertia * rhs_x - coupling * rhs_th, c.total_mass * rhs_th - coupling * rhs_x, inv_det


def euler(q: jax.Array, v: jax.Array, acc: jax.Array, inv_det: jax.Array, dt: float) -> tuple[jax.Array, jax.Array]:
    """Semi-implicit Euler, as MuJoCo: velocities first, positions with the new velocities; on one coordinate
    or on the stacked ``[x, θ]`` vectors alike."""
    v = v + dt * (acc * inv_det)
    return q + dt * v, v
