"""Python floats as an array module: ``FLOATS`` is the ``xp`` a task's per-coordinate functions take when one env
steps on the host (:class:`jaxrobo.interop.gym_adapter.JaxroboEnv` with ``engine="numpy"``).

One env's state is a handful of numbers; as Python floats (IEEE float64) each operation costs tens of nanoseconds,
where a numpy scalar costs hundreds and a JAX call microseconds. Only the functions those per-coordinate functions
use are here. ``minimum``/``maximum`` are Python's ``min``/``max``, which do not propagate a NaN as ``jnp`` does:
a host step checks its state for non-finite values itself.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

#: ``xp`` over Python floats: ``sin``, ``cos``, ``minimum``, ``maximum``.
FLOATS = SimpleNamespace(sin=math.sin, cos=math.cos, minimum=min, maximum=max)
