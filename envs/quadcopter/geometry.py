"""The quadcopter's geometry, written once per coordinate over an array module ``xp``: Euler angles of a
quaternion, exact ray tests against the ground, axis-aligned boxes and vertical cylinders, and a point's
distance to an obstacle.

Every path runs these functions: the robot's and the Goto tasks' hooks (:mod:`envs.quadcopter.robot`,
``xp = jax.numpy``, under ``vmap``), the Pallas task kernel (:mod:`envs.quadcopter.goto_kernel`, ``jax.numpy`` on
one ``[block]`` vector per coordinate: its Triton lowering has no slice or gather within a block, hence per
coordinate) and the native-MuJoCo port (:mod:`envs.quadcopter.native`, ``xp = numpy`` on float64 scalars). This
module imports no JAX, so the native port runs without it; ``xp`` needs ``where``, ``abs``, ``minimum``,
``maximum``, ``sqrt``, ``arctan2``, ``arcsin`` and ``clip``.

A point or a direction is a sequence of 3 coordinates. A direction's component may be known while tracing:
``None`` for a component known to be 0 (a level ray's vertical one), a Python ``float`` for a known value (the
down ray's ``-1.0``); the tests that such a component decides are then chosen in Python and not computed (the
kernel's level and down rays). Any other value (an array, a numpy scalar) is the general case, tested per value.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

#: "No hit" / "no obstacle": a distance beyond any range the tasks read.
INF = 1e6
#: A direction component below this is treated as parallel to the axis' planes by the ray tests.
PARALLEL = 1e-9
#: Obstacle kinds (:class:`envs.quadcopter.robot.Obstacles`).
BOX, CYLINDER = 0, 1
#: Unit sonar rays in the body frame: forward, forward-left 35°, forward-right 35°, down.
SONAR_RAYS = np.array([[1.0, 0.0, 0.0], [np.cos(0.61), np.sin(0.61), 0.0], [np.cos(0.61), -np.sin(0.61), 0.0],
                       [0.0, 0.0, -1.0]], np.float32)


def _known(d: Any) -> bool:
    """A direction component whose value is known while tracing (exactly a Python float, not a numpy scalar)."""
    return type(d) is float


# ---- pose ----------------------------------------------------------------------------------------------
def roll_terms(w, x, y, z) -> tuple:
    """``(y, x)`` with ``roll = atan2(y, x)`` of a wxyz quaternion (ZYX convention)."""
    return 2 * (w * x + y * z), 1 - 2 * (x * x + y * y)


def sin_pitch(w, x, y, z):
    """``sin(pitch)`` of a wxyz quaternion (ZYX convention; the caller clips it to [-1, 1])."""
    return 2 * (w * y - z * x)


def yaw_terms(w, x, y, z) -> tuple:
    """``(y, x)`` with ``yaw = atan2(y, x)`` of a wxyz quaternion (ZYX convention)."""
    return 2 * (w * z + x * y), 1 - 2 * (y * y + z * z)


def euler(xp: Any, w, x, y, z) -> tuple:
    """``(roll, pitch, yaw)`` (rad) of a wxyz quaternion, ZYX convention (tf's ``euler_from_quaternion``). The
    controller (:func:`envs.quadcopter.dynamics.controller`) takes cosines and sines from the same terms
    without the angles."""
    return (xp.arctan2(*roll_terms(w, x, y, z)), xp.arcsin(xp.clip(sin_pitch(w, x, y, z), -1.0, 1.0)),
            xp.arctan2(*yaw_terms(w, x, y, z)))


def wrap_angle(a):
    """Angle wrapped to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


# ---- exact ray tests -----------------------------------------------------------------------------------
def safe_inv(xp: Any, d):
    """``1 / d`` with ``|d|`` held at least :data:`PARALLEL` (its sign kept): finite for a parallel component."""
    return 1.0 / xp.where(xp.abs(d) < PARALLEL, xp.where(d < 0, -PARALLEL, PARALLEL), d)


def slab(xp: Any, o, d, c, h) -> tuple:
    """One axis of :func:`ray_box`: ``(t_near, t_far)`` of the slab ``|x - c| <= h``. A ray parallel to it is
    inside for all t if its origin is within the closed range (a ray grazing along a face touches the box), else
    never."""
    in_slab = xp.abs(o - c) <= h
    outside_near = xp.where(in_slab, -INF, INF)
    if d is None:
        return outside_near, xp.where(in_slab, INF, -INF)
    inv = 1.0 / d if _known(d) else safe_inv(xp, d)
    t1 = (c - h - o) * inv
    t2 = (c + h - o) * inv
    if _known(d):
        return xp.minimum(t1, t2), xp.maximum(t1, t2)
    parallel = xp.abs(d) < PARALLEL
    return (xp.where(parallel, outside_near, xp.minimum(t1, t2)),
            xp.where(parallel, xp.where(in_slab, INF, -INF), xp.maximum(t1, t2)))


def ray_box(xp: Any, o: Sequence, d: Sequence, c: Sequence, h: Sequence):
    """Slab test: distance along the ray ``o + t d`` to the axis-aligned box of center ``c`` and half extents
    ``h`` (0 when the origin is inside, :data:`INF` on a miss)."""
    near, far = zip(*(slab(xp, o[i], d[i], c[i], h[i]) for i in range(3)))
    t_near = xp.maximum(xp.maximum(near[0], near[1]), near[2])
    t_far = xp.minimum(xp.minimum(far[0], far[1]), far[2])
    hit = (t_near <= t_far) & (t_far >= 0)
    return xp.where(hit, xp.maximum(t_near, 0.0), INF)


def ray_cylinder(xp: Any, p: Sequence, d: Sequence, center: Sequence, radius, half_height):
    """Distance along the ray ``p + t d`` to a vertical solid cylinder: side wall, both caps, or 0 from inside;
    :data:`INF` on a miss. A level ray (``d[2]`` None) meets the side wall only, a vertical one (``d[0]``,
    ``d[1]`` None, ``d[2]`` known) the caps only; they skip the other tests."""
    o = [p[i] - center[i] for i in range(3)]
    if d[2] is None:  # level: the side wall only (a level ray never meets a cap)
        r2 = radius * radius
        c = o[0] * o[0] + o[1] * o[1] - r2
        inside = (c <= 0) & (xp.abs(o[2]) <= half_height)
        a = d[0] * d[0] + d[1] * d[1]
        b = 2 * (o[0] * d[0] + o[1] * d[1])
        disc = b * b - 4 * a * c
        t_side = (-b - xp.sqrt(xp.maximum(disc, 0.0))) / (2 * xp.maximum(a, 1e-12))
        side_ok = (a > 1e-12) & (disc >= 0) & (t_side >= 0) & (xp.abs(o[2]) <= half_height)
        t = xp.where(side_ok, t_side, INF)
    elif d[0] is None and d[1] is None:  # vertical: the caps only
        r2 = radius * radius
        c = o[0] * o[0] + o[1] * o[1] - r2
        inside = (c <= 0) & (xp.abs(o[2]) <= half_height)
        inv_z = 1.0 / d[2]
        xy_in = o[0] * o[0] + o[1] * o[1] <= r2
        caps = [(half_height - o[2]) * inv_z, (-half_height - o[2]) * inv_z]
        t = xp.minimum(xp.where((caps[0] >= 0) & xy_in, caps[0], INF),
                       xp.where((caps[1] >= 0) & xy_in, caps[1], INF))
    else:  # any direction: the side wall at its entry height, and both caps
        a = d[0] ** 2 + d[1] ** 2
        b = 2 * (o[0] * d[0] + o[1] * d[1])
        c = o[0] ** 2 + o[1] ** 2 - radius**2
        disc = b * b - 4 * a * c
        t_side = (-b - xp.sqrt(xp.maximum(disc, 0.0))) / (2 * xp.maximum(a, 1e-12))
        z_side = o[2] + t_side * d[2]
        side_ok = (a > 1e-12) & (disc >= 0) & (t_side >= 0) & (xp.abs(z_side) <= half_height)
        inv_z = safe_inv(xp, d[2])
        vertical = xp.abs(d[2]) > PARALLEL
        t = xp.where(side_ok, t_side, INF)
        cap_t = INF
        for cap in ((half_height - o[2]) * inv_z, (-half_height - o[2]) * inv_z):
            cx, cy = o[0] + cap * d[0], o[1] + cap * d[1]
            cap_t = xp.minimum(cap_t, xp.where((cap >= 0) & (cx**2 + cy**2 <= radius**2) & vertical, cap, INF))
        t = xp.minimum(t, cap_t)
        inside = (c <= 0) & (xp.abs(o[2]) <= half_height)
    return xp.where(inside, 0.0, t)


def ray_ground(xp: Any, o: Sequence, d: Sequence):
    """Distance along the ray ``o + t d`` to the plane z = 0 (:data:`INF` if it points up or sideways; 0 from
    below it). A level ray (``d[2]`` None) meets it only from below; the down ray (``d[2] == -1.0``) at the
    altitude."""
    if d[2] is None:
        return xp.where(o[2] <= 0, 0.0, INF)
    if _known(d[2]) and d[2] == -1.0:
        return xp.where(o[2] > 0, o[2], 0.0)
    t = -o[2] * safe_inv(xp, d[2])
    hit = (d[2] < -PARALLEL) | (o[2] <= 0)
    return xp.where(hit, xp.maximum(t, 0.0) * (o[2] > 0), INF)


def point_distance(xp: Any, p: Sequence, center: Sequence, size: Sequence, kind: str):
    """Euclidean distance from a point to one obstacle's surface (0 inside): ``kind`` 'box' (``size``: half
    extents) or 'cylinder' (``size``: radius, unused, half height)."""
    q = [xp.abs(p[i] - center[i]) for i in range(3)]
    over_z = xp.maximum(q[2] - size[2], 0.0)
    if kind == "box":
        over = [xp.maximum(q[i] - size[i], 0.0) for i in range(2)]
        return xp.sqrt(over[0] * over[0] + over[1] * over[1] + over_z * over_z)
    radial = xp.maximum(xp.sqrt(q[0] * q[0] + q[1] * q[1]) - size[0], 0.0)
    return xp.sqrt(radial * radial + over_z * over_z)
