"""The stay-up task's rules per coordinate, written once: the task's hooks (:mod:`envs.cartpole.stay_up`) call
them on one env's values, the whole-chunk kernel (:mod:`envs.cartpole.kernel`) on ``[block]`` vectors of a Pallas
program, the host step (:mod:`envs.cartpole.host`) on Python floats. Each takes scalars or same-shape arrays and
the parameters as values (a kernel holds them as scalars read from its parameter vector, not as a params pytree);
``xp`` is the array module (``jax.numpy``, ``numpy``, or :data:`jaxrobo.core.scalar.FLOATS` for Python floats).
This module imports no JAX: an exported policy's runner (:func:`jaxrobo.export.runner_source`) computes the
robot's command and observation with it too."""
from __future__ import annotations

#: The reward of every step, the terminating one included.
REWARD = 1.0

#: Action ``i`` adds ``ACTION_STEPS[i] * pos_step`` to the cart command (left, right, left big, right big).
ACTION_STEPS = (-1.0, 1.0, -10.0, 10.0)


def command_after(command, step, pos_step, max_base_velocity, xp):
    """The cart command after an action whose step (:data:`ACTION_STEPS`) is ``step``: ``pos_step`` times it added,
    then, for a velocity command (``max_base_velocity`` not None), clipped to ``±max_base_velocity``."""
    command = command + step * pos_step
    if max_base_velocity is None:
        return command
    return xp.minimum(xp.maximum(command, -max_base_velocity), max_base_velocity)


def fell(x, angle, min_base_pose_x, max_base_pose_x, min_pole_angle, max_pole_angle):
    """Whether the episode ends: the cart at or beyond either end of its range, or the pole angle outside
    ``(min_pole_angle, max_pole_angle)``."""
    return (x <= min_base_pose_x) | (x >= max_base_pose_x) | (angle <= min_pole_angle) | (angle >= max_pole_angle)


def observation(sensors, round_obs, xp):
    """The observation from the joint sensors ``[cart_x, cart_v, pole_angle, pole_angular_velocity]``: cast to
    float32, rounded to 0.1 with ``round_obs`` (the seed's rounding). ``xp``: ``jax.numpy`` or ``numpy``."""
    obs = sensors.astype(xp.float32)
    return xp.round(obs, 1) if round_obs else obs
