"""What a task's step for one env on the host shares (:attr:`jaxrobo.task.env.TaskEnv.host_step`, what
``gymnasium.make(id, engine="numpy")`` steps): :class:`HostStep`.

A host step runs the task's own per-coordinate functions (action map, observation, outcome, reward, and the
robot's equations) on Python floats, with no JAX call: the physics is the backend's own on the host, the closed
form written out once as plain arithmetic (:func:`jaxrobo.core.scalar.straight_line`) or native MuJoCo
(:class:`jaxrobo.interop.native.NativeSim`, the C engine MJX reimplements) on the robot's compiled model.

Precision: float64 (Python floats, MuJoCo's doubles) where the JAX path computes in float32. On the host a Python
float is the fastest number there is (a numpy float32 scalar costs several times as much per operation), and
float64 is the precision the closed forms are checked in against native MuJoCo; the observation is cast to float32
as the task's is. The two engines therefore agree to float32 rounding, not bit for bit
(``tests/test_gym_host_step.py`` states each task's tolerance). Episodes start from the JAX reset's state, so seeds
mean the same thing through both engines. Domain randomisation is not modelled (refused). This module imports no
JAX.
"""
from __future__ import annotations

from typing import Any, Callable


class HostStep:
    """The base of a task's host step. A subclass names the backends it runs (:attr:`backends`), builds its
    written-out control step in :meth:`_closed_form` (``self.native``, its :class:`NativeSim`, None on a closed
    form) and adds ``set_params(params)``, ``start(states, i)``, ``step(action)`` and ``joints()``."""

    #: The backends whose physics runs on the host.
    backends: tuple[str, ...] = ()

    @classmethod
    def unsupported(cls, env: Any) -> str | None:
        """Why ``env`` cannot step on the host (None: it can)."""
        if env.randomised:
            return "the host step does not model domain randomisation (randomise=true)"
        backend = env.robot.sim.backend
        if backend not in cls.backends:
            return (f"backend={backend!r} has no host physics; the host step runs backend "
                    f"{' or '.join(map(repr, cls.backends))}")
        return None

    def __init__(self, env: Any):
        why = self.unsupported(env)
        if why is not None:
            raise ValueError(f"{env.name}: {why}")
        self.native: Any = None
        self.advance: Callable[..., tuple] | None = None

    def _closed_form(self) -> Callable[..., tuple]:
        """The control step of the closed form, written out (called where ``self.native`` is None)."""
        raise NotImplementedError

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "advance": None}  # generated code does not pickle: written out again

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        if self.native is None:
            self.advance = self._closed_form()
