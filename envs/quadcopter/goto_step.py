"""The Goto tasks' step, written once per coordinate over an array module ``xp``: the action map (the seed's
five Twists), the observation (goal distance, bearing and height difference, the level sonars, v2's
``goal_clear``), the outcome (arrival; a crash into the ground or an obstacle, leaving the workspace, the altitude
and inclination limits) and the reward (v1's terms, v2's two shaping terms).

Three callers run it: the tasks' hooks (:class:`envs.quadcopter.goto.QuadcopterGoto`, ``xp = jax.numpy`` under
``vmap``), the Pallas task kernel (:func:`envs.quadcopter.goto_kernel.task_step`, ``jax.numpy`` on ``[block]``
vectors) and the native-MuJoCo port (:class:`envs.quadcopter.native.NativeGoto`, ``numpy`` float64). This module
imports no JAX. A point is 3 coordinates, the parameters a mapping by name (:data:`V1_PARAMS`, :data:`V2_PARAMS`),
the obstacles are reached through the caller's ``fold`` (:func:`observe`): the kernel loops over an index, the
hooks vmap over the obstacle arrays, the native port loops in Python; each takes the minimum of what
:func:`obstacle_distances` gives per obstacle.

The rays are the task's own: level (gimballed) sonars, rotated by the heading only, so their vertical component is
known to be 0 and the down ray is ``(0, 0, -1)`` (:mod:`envs.quadcopter.geometry` drops the tests those decide).
"""
from __future__ import annotations

from typing import Any, Callable, Iterator, Sequence

import numpy as np

from envs.quadcopter.geometry import BOX, INF, SONAR_RAYS, point_distance, ray_box, ray_cylinder, ray_ground, \
    wrap_angle

#: The seed's five Twist actions ``[vx, vy, vz, yaw_rate]`` per unit ``speed_value``: forward, turn left, turn
#: right, up, down. Turning keeps the seed's small forward speed of 0.05 m/s (not scaled).
ACTION_NAMES = ("forward", "left", "right", "up", "down")
ACTION_SCALE = np.array([[1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 0, -1], [0, 0, 1, 0], [0, 0, -1, 0]], np.float32)
ACTION_FIXED = np.array([[0, 0, 0, 0], [0.05, 0, 0, 0], [0.05, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]], np.float32)

#: The parameters (:class:`envs.quadcopter.goto.Params`) a step reads.
V1_PARAMS = ("speed_value", "goal_tolerance", "workspace", "max_altitude", "max_incl", "drone_radius",
             "sonar_range", "progress_reward", "step_cost", "altitude_cost", "arrival_bonus", "crash_penalty")
#: v2's (:class:`envs.quadcopter.goto_v2.Params`): v1's, the goal_clear margin, the two shaping weights and the
#: lead of goal_dz.
V2_PARAMS = V1_PARAMS + ("clear_margin", "heading_reward", "climb_reward", "dz_lead")

#: The caller's reduction over the obstacles: ``fold(distances, init)`` with ``distances(kind, center, size,
#: active)`` one obstacle's distances (an iterator); returns their elementwise minimum, a tuple like ``init``.
Fold = Callable[[Callable[..., tuple], tuple], tuple]


def loop_fold(xp: Any, obstacles: dict) -> Fold:
    """The obstacles' fold of one env on the host (:func:`observe`): a Python loop over ``obstacles``' ``kind``,
    ``center``, ``size`` and ``active`` (arrays of one episode's obstacles)."""

    def fold(distances, nearest):
        for kind, center, size, active in zip(obstacles["kind"], obstacles["center"], obstacles["size"],
                                              obstacles["active"]):
            nearest = tuple(xp.minimum(m, t) for m, t in zip(nearest, distances(kind, center.tolist(),
                                                                                  size.tolist(), active)))
        return nearest

    return fold


def twist(xp: Any, action, speed) -> list:
    """The seed's Twist ``[vx, vy, vz, yaw_rate]`` of an action index (0 forward, 1 left, 2 right, 3 up, 4 down)
    at ``speed`` (an action outside 0-4 reads as 0)."""
    out = []
    for j in range(4):
        value = None
        for k in range(ACTION_SCALE.shape[0]):
            scale, fixed = float(ACTION_SCALE[k, j]), float(ACTION_FIXED[k, j])
            v_k = scale * speed + fixed if scale != 0.0 else speed * 0.0 + fixed
            value = v_k if value is None else xp.where(action == k, v_k, value)
        out.append(value)
    return out


def kinds_of(obstacle_kind: str) -> tuple[str, ...]:
    """The obstacle kinds a layout holds (``mixed``: both, chosen per obstacle by its ``kind``)."""
    return ("box", "cylinder") if obstacle_kind == "mixed" else (obstacle_kind,)


def level_rays(xp: Any, yaw) -> list:
    """The sonar rays (:data:`~envs.quadcopter.geometry.SONAR_RAYS`) rotated by the heading's quaternion (its
    matrix written out: x = y = 0): level rays ``(dx, dy, None)`` and the down ray ``(None, None, -1.0)``."""
    hw, hz = xp.cos(yaw / 2), xp.sin(yaw / 2)
    r_cos, r_sin = 1 - 2 * (hz * hz), 2 * (hw * hz)
    rays = []
    for rx, ry, rz in SONAR_RAYS.tolist():
        if rz != 0.0:  # the down ray (0, 0, -1)
            rays.append((None, None, float(np.float32(rz))))
            continue
        dx = [t for t in (rx * r_cos if rx else None, -(ry * r_sin) if ry else None) if t is not None]
        dy = [t for t in (rx * r_sin if rx else None, ry * r_cos if ry else None) if t is not None]
        rays.append((sum(dx[1:], dx[0]), sum(dy[1:], dy[0]), None))
    return rays


def goal_ray(xp: Any, delta: Sequence) -> tuple:
    """``(level distance to the goal, the level unit ray towards it)``: v2's ``goal_clear`` ray."""
    level = xp.sqrt(delta[0] * delta[0] + delta[1] * delta[1])
    unit = xp.maximum(level, 1e-6)
    return level, (delta[0] / unit, delta[1] / unit, None)


def obstacle_distances(xp: Any, pos: Sequence, rays: Sequence, kinds: Sequence[str], kind, center: Sequence,
                       size: Sequence, active, towards: tuple | None = None, grow=None) -> Iterator:
    """One obstacle's distances (:data:`~envs.quadcopter.geometry.INF` where it is not ``active``): along each
    ray, along ``towards`` to the obstacle grown sideways by ``grow`` (if given), and from ``pos`` to its surface.
    ``kinds``: the layout's (:func:`kinds_of`); with both, ``kind`` chooses."""
    found = {}
    for name in kinds:
        ts = []
        for d in rays:
            if name == "box":
                ts.append(ray_box(xp, pos, d, center, size))
            else:
                ts.append(ray_cylinder(xp, pos, d, center, size[0], size[2]))
        if towards is not None:
            grown = [size[0] + grow, size[1] + grow, size[2]]
            ts.append(ray_box(xp, pos, towards, center, grown) if name == "box"
                      else ray_cylinder(xp, pos, towards, center, grown[0], grown[2]))
        ts.append(point_distance(xp, pos, center, size, name))
        found[name] = ts
    ts = found[kinds[0]] if len(kinds) == 1 else \
        [xp.where(kind == BOX, b, cyl) for b, cyl in zip(found["box"], found["cylinder"])]
    # An iterator: a fold taking the minimum as it goes masks and folds each distance in turn (the kernel's order).
    return (xp.where(active, t, INF) for t in ts)


def observe(xp: Any, pos: Sequence, yaw, vz, goal: Sequence, p: Any, v2: bool, kinds: Sequence[str], fold: Fold,
            sonars: Sequence | None = None) -> tuple[list, Any, Any]:
    """The observation ``[goal_dist, goal_bearing, goal_dz, sonar_forward, sonar_left, sonar_right, sonar_down]``
    (v2: ``goal_dz - dz_lead * vz`` and ``goal_clear`` after the sonars) of the drone at ``pos`` with heading
    ``yaw`` and vertical velocity ``vz``; ``sonars``: ranges read elsewhere (the ROS topics) instead of the rays.
    Returns ``(obs, goal distance, distance to the nearest obstacle's surface)``."""
    delta = [goal[i] - pos[i] for i in range(3)]
    dist = xp.sqrt(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2])
    bearing = wrap_angle(xp.arctan2(delta[1], delta[0]) - yaw)
    rays = level_rays(xp, yaw) if sonars is None else []
    level, towards = goal_ray(xp, delta) if v2 else (None, None)
    grow = p["drone_radius"] + p["clear_margin"] if v2 else None
    n_out = len(rays) + int(v2) + 1
    nearest = fold(lambda kind, center, size, active: obstacle_distances(
        xp, pos, rays, kinds, kind, center, size, active, towards, grow), tuple(pos[0] * 0.0 + INF
                                                                            for _ in range(n_out)))
    sonar_range = p["sonar_range"]
    # v2's goal_dz is read where the climb stops: vz is the world vertical velocity (qvel's linear part).
    obs = [dist, bearing, delta[2] - p["dz_lead"] * vz if v2 else delta[2]]
    if sonars is None:
        for d, t in zip(rays, nearest):
            obs.append(xp.minimum(xp.minimum(ray_ground(xp, pos, d), t), sonar_range))
    else:
        obs.extend(sonars)
    if v2:
        ray = nearest[len(rays)]
        obs.append(xp.where(ray < level, xp.minimum(ray, sonar_range), sonar_range))
    return obs, dist, nearest[-1]


def outcome(xp: Any, pos: Sequence, roll, pitch, dist, point_dist, p: Any) -> tuple:
    """``(arrived, failed)``: failed = the drone, a sphere of ``drone_radius``, touches the ground or an obstacle
    (``point_dist``: its center's distance to the nearest surface), leaves the workspace or breaks the altitude
    or inclination limit; arrived = within ``goal_tolerance`` of the goal (``dist``) and not failed."""
    pz = pos[2]
    radius = p["drone_radius"]
    ws = p["workspace"]
    outside = (xp.abs(pos[0]) > ws) | (xp.abs(pos[1]) > ws)
    limits = (pz > p["max_altitude"]) | (xp.abs(roll) >= p["max_incl"]) | (xp.abs(pitch) >= p["max_incl"])
    failed = (pz <= radius) | (point_dist <= radius) | outside | limits
    arrived = (dist < p["goal_tolerance"]) & ~failed
    return arrived, failed


def reward(xp: Any, p: Any, task: Any, obs: Sequence, dist, pz, arrived, failed, v2: bool) -> tuple[Any, dict]:
    """The reward and the task variables after it: ``progress_reward`` per m the goal distance shrank,
    ``- step_cost``, ``- altitude_cost`` per m of altitude ``pz``, ``+ arrival_bonus``, ``- crash_penalty``; v2
    adds ``heading_reward`` per rad ``|goal_bearing|`` shrank and ``climb_reward`` per m ``|goal_dz|`` shrank.
    ``task``: the last ``prev_dist``, ``arrived``, ``crashed`` (v2 ``prev_bearing``, ``prev_dz``) by name."""
    r = (p["progress_reward"] * (task["prev_dist"] - dist) - p["step_cost"] - p["altitude_cost"] * pz
         + xp.where(arrived, p["arrival_bonus"], 0.0) - xp.where(failed, p["crash_penalty"], 0.0))
    new_task = {"prev_dist": dist, "arrived": task["arrived"] | arrived, "crashed": task["crashed"] | failed}
    if v2:
        b_abs, dz_abs = xp.abs(obs[1]), xp.abs(obs[2])
        r = r + (p["heading_reward"] * (task["prev_bearing"] - b_abs) + p["climb_reward"] * (task["prev_dz"] - dz_abs))
        new_task.update(prev_bearing=b_abs, prev_dz=dz_abs)
    return r, new_task
