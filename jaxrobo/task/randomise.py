"""Domain randomisation: each episode's physical parameters drawn at every reset from ranges in the task's Params.

A task that offers it declares, in its ``Params``, one traced ``[low, high]`` range per randomisable quantity
(:func:`jaxrobo.core.struct.range_param`, named ``rand_<name>``: ``rand_mass``, ``rand_wind``, ``rand_obs_noise``...)
and, in its ``Options``, the static switch ``randomise``. With ``randomise`` off (the default) nothing here is
traced: the step is the one it always was, bit for bit. With it on:

* at every reset, :func:`draw` takes one value per range, uniformly in ``[low, high]``, from a key folded out of
  the reset key (so the reset's other draws, pose, goal and obstacles, keep their keys), and the env state holds
  them (``EnvState.domain``): each episode keeps its own physics until its next reset;
* every control step hands them to the robot (:meth:`jaxrobo.task.robot.Robot.advance`, ``domain=``), which maps
  its names onto its simulator (:meth:`jaxrobo.task.robot.Robot.sim_physics`: scaled masses, gains, a wind force on
  the closed forms; edited ``mjx.Model`` / ``mjx.Data`` fields under MJX, the way MuJoCo Playground's randomisers
  build a batched model);
* ``obs_noise`` (if the task declares it) is the standard deviation of Gaussian noise added to every component of
  the observation the agent sees, fresh at every step (reward and termination read the true state).

The ranges are traced parameters: a sweep can vary the ranges themselves, and a zero-width range ``[v, v]`` pins
a quantity at ``v`` (what ``jaxrobo eval`` uses to fly a policy on shifted physics). A robot names what it can
randomise per backend (:meth:`jaxrobo.task.robot.Robot.randomisable`); asking for more is refused at construction.
The Pallas kernels take the draws as per-env inputs, so a randomised run keeps its kernel: the quadcopter's
control-step and Goto task kernels read the physics :meth:`~jaxrobo.task.robot.Robot.sim_physics` gives (the
noise is added around them, as :meth:`jaxrobo.task.env.TaskEnv.step` adds it), and the cart-pole's chunk kernel,
which resets in-kernel, draws the domain and the noise from the same keys as :func:`draw` and :func:`noisy`
(:data:`DRAW_TAG`, :data:`NOISE_TAG`). With ``randomise`` off they have none of these inputs.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxrobo.core.struct import range_param, rules

#: Prefix of a randomisation range's field name in a task's Params.
PREFIX = "rand_"
#: Quantities the task layer handles itself (not physics): the observation noise's standard deviation.
OBS_NOISE = "obs_noise"
#: Suffix of the direction drawn beside a directional quantity's magnitude.
HEADING = "_heading"
#: Folded into the reset key for the draws, and into the env's key for the observation noise (public: the
#: cart-pole's chunk kernel, which resets in-kernel, draws from the same keys).
DRAW_TAG, NOISE_TAG = 0x5244, 0x4E53


def obs_noise_range() -> Any:
    """The ``rand_obs_noise`` field of a task's Params (:data:`OBS_NOISE`, handled by the task layer, so one
    declaration for every task): the standard deviation of the observation noise, off by default."""
    return range_param((0.0, 0.0), low=0.0, high=10.0,
                       doc="std of Gaussian noise on every observation component, fresh each step")


def range_fields(params_cls: Any) -> tuple[str, ...]:
    """The names (without :data:`PREFIX`) of the randomisation ranges a Params class declares, in field order."""
    return tuple(name[len(PREFIX):] for name, rule in rules(params_cls).items()
                 if rule.pair and name.startswith(PREFIX))


def ranges(params: Any) -> dict[str, Any]:
    """``{name: (low, high)}`` of every randomisation range in ``params`` (values may be traced)."""
    return {name: getattr(params, PREFIX + name) for name in range_fields(type(params))}


def changed(params: Any) -> list[str]:
    """The fields of host ``params`` whose range differs from its declared default (empty: all at their defaults,
    which pin every quantity at its nominal value)."""
    defaults = {f.name: f.default for f in dataclasses.fields(type(params))}
    out = []
    for name, r in ranges(params).items():
        values = [float(v) for v in np.asarray(r, np.float64).reshape(-1)]
        if values != [float(v) for v in defaults[PREFIX + name]]:
            out.append(PREFIX + name)
    return out


def uniform(key: jax.Array, bounds: Any) -> jax.Array:
    """One value uniformly in ``[low, high]``; exactly ``low`` when the two are equal."""
    b = jnp.asarray(bounds, jnp.float32)
    return b[0] + jax.random.uniform(key, (), jnp.float32) * (b[1] - b[0])


def draw(key: jax.Array, params: Any, directional: tuple[str, ...] = ()) -> dict[str, jax.Array]:
    """One episode's values, ``{name: value}``, one uniform draw per range of ``params`` from ``key`` (the reset's
    key, folded, so the reset's own splits are unchanged). Each name in ``directional`` (a force such as a wind)
    also gets ``<name>_heading``, a direction uniform in [-pi, pi)."""
    base = jax.random.fold_in(key, DRAW_TAG)
    out = {}
    for i, (name, bounds) in enumerate(ranges(params).items()):
        out[name] = uniform(jax.random.fold_in(base, 2 * i), bounds)
        if name in directional:
            out[name + HEADING] = uniform(jax.random.fold_in(base, 2 * i + 1), (-jnp.pi, jnp.pi))
    return out


def physics_of(domain: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """The physical quantities of a drawn domain: everything but the observation noise."""
    return {k: v for k, v in domain.items() if k != OBS_NOISE}


def noisy(obs: jax.Array, domain: Any, key: jax.Array, steps: jax.Array) -> jax.Array:
    """``obs`` with the domain's Gaussian observation noise (none if the task declares no ``obs_noise``), fresh for
    each step: the key is the env state's, folded with the step count."""
    if not domain or OBS_NOISE not in domain:
        return obs
    k = jax.random.fold_in(jax.random.fold_in(key, NOISE_TAG), steps)
    return (obs + domain[OBS_NOISE] * jax.random.normal(k, obs.shape, jnp.float32)).astype(obs.dtype)


def check(env: Any) -> None:
    """Refuse (ValueError naming the field) a task whose randomisation the robot cannot do, or ranges given while
    ``randomise`` is off (they would be silently ignored)."""
    on = bool(getattr(env.options, "randomise", False))
    names = range_fields(type(env.default_params))
    if not on:
        given = changed(env.default_params)
        if given:
            raise ValueError(f"{given[0]}={list(getattr(env.default_params, given[0]))}: a randomisation range is "
                             "given but randomise is false, which reads none; set randomise=true")
        return
    if not names:
        raise ValueError(f"randomise=true: {type(env).__name__} declares no randomisation ranges")
    can = set(env.robot.randomisable()) | {OBS_NOISE}
    missing = [PREFIX + n for n in names if n not in can]
    if missing:
        raise ValueError(f"randomise=true: backend={env.options.backend!r} cannot randomise {', '.join(missing)}; "
                         f"it can randomise {', '.join(PREFIX + n for n in sorted(can))}")


def pinned(params: Any, values: dict[str, float]) -> Any:
    """``params`` with each named range pinned at a value (``{name: v}`` → ``rand_<name> = (v, v)``)."""
    known = range_fields(type(params))
    for name in values:
        if name not in known:
            raise ValueError(f"{name}: not a randomisation range of {type(params).__name__}; it has "
                             f"{', '.join(known) or 'none'}")
    return dataclasses.replace(params, **{PREFIX + n: (float(v), float(v)) for n, v in values.items()})
