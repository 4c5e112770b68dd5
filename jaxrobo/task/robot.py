"""The robot layer (openai_ros' robot env): a model, its actuators, a low-level controller and sensors.

A robot owns a :class:`~jaxrobo.physics.sim.Simulator`; tasks talk to the robot, never to the physics backend, so the
same task runs on MJX, on a Brax pipeline or on the robot's own closed form.

Public surface: subclass :class:`Robot`; build its simulator in ``__init__`` with
:func:`jaxrobo.physics.sim.make_simulator` from a model loaded by :func:`jaxrobo.physics.sim.load_model` (the robot
module owns its MJCF's path), and override :meth:`Robot.controller` (runs every physics substep) and
:meth:`Robot.read_sensors`. Tasks call :meth:`Robot.advance` and :meth:`Robot.read_sensors`; ``robot.sim`` is there for
tasks that need the state's coordinates or ``forward`` (MJX). ``_check_all_systems_ready`` keeps the seed's name and is
called by the task layer.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxrobo.physics.sim import BatchedAdvance, Simulator


class Robot:
    """Base robot: actuators take the task's command directly; subclasses add controllers and sensors."""

    #: The control step (controller and physics substeps) over a batch of envs as one kernel, where the robot
    #: has one for its backend (the rigid quadcopter's Pallas kernel): ``(states [n], commands [n]) -> states``.
    #: Under ``ExecutionPlan(fused="pallas")`` a vmapped :meth:`advance` calls it once on the whole batch (see
    #: :meth:`jaxrobo.physics.sim.Simulator.advance`); None: the simulator's own substep loop always.
    advance_kernel: BatchedAdvance | None = None

    def __init__(self, sim: Simulator):
        self.sim = sim

    def controller(self, pipeline_state: Any, command: jax.Array) -> jax.Array:
        """Map a task command to actuator controls; runs every physics substep. Default: pass through."""
        return command

    #: Randomisable quantities that are forces with a direction (:func:`jaxrobo.task.randomise.draw` adds one).
    directional: tuple[str, ...] = ()

    def advance(self, pipeline_state: Any, command: jax.Array, domain: dict[str, jax.Array] | None = None) -> Any:
        """Apply ``command`` for one control step (the seed's unpause → move → wait → pause). ``domain``: the
        episode's randomised physical quantities (:mod:`jaxrobo.task.randomise`), mapped onto the simulator by
        :meth:`sim_physics`; None: the model as loaded. The robot's kernel runs where the plan runs it, with a
        domain only if it takes one (``advance_kernel.takes_physics``)."""
        if domain is None:
            return self.sim.advance(pipeline_state, command, self.controller, kernel=self.advance_kernel)
        return self.sim.advance(pipeline_state, command, self.controller, kernel=self.advance_kernel,
                                physics=self.sim_physics(domain))

    def randomisable(self) -> tuple[str, ...]:
        """The physical quantities this robot can randomise on its backend (the names of a task's ``rand_<name>``
        ranges); none by default."""
        return ()

    def sim_physics(self, domain: dict[str, jax.Array]) -> Any:
        """The simulator's form of a drawn domain (its ``physics_step``'s ``physics`` argument)."""
        raise NotImplementedError(f"{type(self).__name__} randomises nothing")

    def read_sensors(self, pipeline_state: Any) -> Any:
        """What the robot senses; subclasses return named quantities."""
        return {"qpos": self.sim.qpos(pipeline_state), "qvel": self.sim.qvel(pipeline_state)}

    def _check_all_systems_ready(self, pipeline_state: Any) -> jax.Array:
        """True when the physics state is usable (all finite); the seed waited for ROS topics here instead."""
        return (jnp.all(jnp.isfinite(self.sim.qpos(pipeline_state)))
                & jnp.all(jnp.isfinite(self.sim.qvel(pipeline_state))))
