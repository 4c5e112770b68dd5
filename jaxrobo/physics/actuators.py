"""MuJoCo's joint actuators in closed form, for the hand-written backends (:class:`jaxrobo.physics.sim.ClosedFormSim`):
what ``mj_fwdActuation`` computes for an actuator with a joint transmission, a fixed gain and no or an affine
bias, read from the compiled :class:`mujoco.MjModel`, so the MJCF stays the single source of truth.

For each actuator: the control clamped to its ``ctrlrange``, ``force = gain u + b0 + b1 length + b2 velocity``
(``length`` and ``velocity`` the gear times the joint's coordinate and rate), the force clamped to its
``forcerange``, and the force times the gear on the joint's coordinate. :func:`joint_actuators` reads them and
refuses an actuator the closed form does not describe; :func:`generalized_forces` computes them over any array
module (``jax.numpy`` in a trace or a Pallas kernel, :data:`jaxrobo.core.scalar.FLOATS` on the host).

Used by the cart-pole's ``analytic`` backend (:mod:`envs.cartpole.dynamics`) and the arm's
(:mod:`envs.arm.dynamics`).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import jax.numpy as jnp
import mujoco
import numpy as np

#: One actuator in Python floats: ``(gear on each coordinate, gain, bias (b0, b1, b2), ctrl (low, high),
#: force (low, high))``, an absent limit infinite.
Actuator = tuple[tuple[float, ...], float, tuple[float, float, float], tuple[float, float], tuple[float, float]]


def joint_actuators(m: mujoco.MjModel, refuse: Callable[[bool, str], None]) -> dict[str, np.ndarray]:
    """The actuators of ``m`` as arrays over its ``nv`` coordinates: ``transmission`` ``[nv, nu]`` (the gear of
    actuator j on coordinate i), ``gain`` ``[nu]``, ``bias`` ``[3, nu]``, ``ctrl_low``/``ctrl_high`` and
    ``force_low``/``force_high`` ``[nu]`` (infinite where unlimited). ``refuse(condition, why)`` raises for an
    actuator the closed form does not describe."""
    nu = m.nu
    transmission = np.zeros((m.nv, nu))
    for i in range(nu):
        refuse(m.actuator_trntype[i] != mujoco.mjtTrn.mjTRN_JOINT, f"actuator {i} must act on a joint")
        refuse(m.actuator_dyntype[i] != mujoco.mjtDyn.mjDYN_NONE, f"actuator {i} has activation dynamics")
        refuse(m.actuator_gaintype[i] != mujoco.mjtGain.mjGAIN_FIXED, f"actuator {i} needs a fixed gain")
        refuse(int(m.actuator_biastype[i]) not in (int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE)),
               f"actuator {i} needs no bias or an affine one")
        transmission[int(m.jnt_dofadr[m.actuator_trnid[i, 0]]), i] = m.actuator_gear[i, 0]
    refuse(bool(np.any(m.jnt_actfrclimited)), "a joint limits its actuators' total force (actuatorfrcrange)")
    affine = (m.actuator_biastype == int(mujoco.mjtBias.mjBIAS_AFFINE))[None, :]
    ctrl_lim = m.actuator_ctrllimited.astype(bool)
    force_lim = m.actuator_forcelimited.astype(bool)
    return dict(transmission=transmission, gain=np.array(m.actuator_gainprm[:, 0]),
                bias=np.where(affine, m.actuator_biasprm[:, :3].T, 0.0),
                ctrl_low=np.where(ctrl_lim, m.actuator_ctrlrange[:, 0], -np.inf),
                ctrl_high=np.where(ctrl_lim, m.actuator_ctrlrange[:, 1], np.inf),
                force_low=np.where(force_lim, m.actuator_forcerange[:, 0], -np.inf),
                force_high=np.where(force_lim, m.actuator_forcerange[:, 1], np.inf))


def actuator_rows(transmission: np.ndarray, gain: np.ndarray, bias: np.ndarray, ctrl_low: np.ndarray,
                  ctrl_high: np.ndarray, force_low: np.ndarray, force_high: np.ndarray) -> tuple[Actuator, ...]:
    """:func:`joint_actuators`' arrays as one :data:`Actuator` per actuator, in Python floats (reading a numpy
    element costs more than the arithmetic of a host step on Python floats)."""
    f = lambda a: tuple(float(v) for v in a)  # noqa: E731
    return tuple((f(transmission[:, j]), float(gain[j]), f(bias[:, j]), (float(ctrl_low[j]), float(ctrl_high[j])),
                  (float(force_low[j]), float(force_high[j]))) for j in range(gain.shape[0]))


def generalized_forces(actuators: Sequence[Actuator], coords: Sequence[Any], rates: Sequence[Any], ctrl: Any,
                       xp: Any = jnp) -> list[Any]:
    """The actuators' forces on each coordinate (``mj_fwdActuation``), ``ctrl[j]`` actuator j's control.

    Written per actuator and coordinate over host constants, so only the non-zero terms are traced and the step
    stays a chain of scalar multiply-adds that XLA fuses; an actuator's length and velocity are computed only
    where its bias reads them. ``coords``/``rates``: scalars or same-shape arrays; ``xp``: the array module."""
    generalized: list[Any] = [0.0] * len(coords)
    for j, (gear, gain, bias, ctrl_range, force_range) in enumerate(actuators):
        u = clip(ctrl[j], *ctrl_range, xp)
        force = gain * u + bias[0]
        if bias[1]:
            force = force + bias[1] * sum(g * coord for g, coord in zip(gear, coords) if g)
        if bias[2]:
            force = force + bias[2] * sum(g * rate for g, rate in zip(gear, rates) if g)
        force = clip(force, *force_range, xp)
        generalized = [f + g * force if g else f for f, g in zip(generalized, gear)]
    return generalized


def clip(value: Any, low: float, high: float, xp: Any = jnp) -> Any:
    """``clip`` that traces nothing for an infinite (absent) limit."""
    if math.isfinite(low):
        value = xp.maximum(value, low)
    if math.isfinite(high):
        value = xp.minimum(value, high)
    return value
