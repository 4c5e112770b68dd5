"""The cart-pole robot (openai_ros' ``CartPoleEnv`` robot env): model, controllers and joint sensors.

The MJCF (``envs/cartpole/cartpole.xml``) states masses, lengths and actuator gains. The seed drove the cart through
one of three ROS controller sets; here each is an actuator in the MJCF and the robot keeps only the one named
by ``control_type``:

* ``velocity`` - the command is the cart's velocity set-point (m/s), tracked by ``F = kv (u - v)``;
* ``position`` - the command is the cart's position set-point (m), tracked by a PD law;
* ``effort``   - the command is the force on the cart (N).

Backends: ``mjx`` (MuJoCo MJX, default), Brax's ``generalized``/``positional``/``spring`` pipelines, or
``analytic`` (:mod:`envs.cartpole.dynamics`: the same model's equations of motion in closed form, ~30× faster
than MJX on 2 CPU cores, 18-38× on an H100, free of the GPU's small-batch latency; agrees with native MuJoCo to
round-off).
"""
from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import mujoco

from envs.cartpole.dynamics import CartPoleSim
from jaxrobo.api import MjxEdit, Robot, backend_choices, load_model, make_simulator

CONTROL_TYPES = ("velocity", "position", "effort")
CART_JOINT = "foot_to_base"
POLE_JOINT = "pole_joint"
#: The robot's MJCF, beside this module.
MJCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "cartpole.xml")
#: The cart-pole's hand-written backend, beside every engine of :mod:`jaxrobo.physics.sim`.
CLOSED_FORM = {"analytic": lambda mj_model, running_step: CartPoleSim(mj_model, CART_JOINT, POLE_JOINT, running_step)}
BACKENDS = backend_choices(CLOSED_FORM)


class CartPoleRobot(Robot):
    """A cart on a slider with a hinged pole; one actuator on the slider, chosen by ``control_type``."""

    def __init__(self, control_type: str = "velocity", backend: str = "mjx", running_step: float = 0.04,
                 timestep: float = 0.01):
        if control_type not in CONTROL_TYPES:
            raise ValueError(f"control_type={control_type!r}: allowed values are {', '.join(CONTROL_TYPES)}")
        self.control_type = control_type
        options = dict(keep_actuators=(control_type,), timestep=timestep)
        mj_model = load_model(MJCF, **options)
        # MJX integrates the model without its visual geoms, camera and light (same dynamics, 1.3-1.5x the MJX
        # steps per second on 2 CPU cores); loaded only if the backend is MJX.
        physics = lambda: load_model(MJCF, physics_only=True, **options)  # noqa: E731
        super().__init__(make_simulator(mj_model, backend, running_step, physics, closed_form=CLOSED_FORM))
        jnt = lambda name: mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, name)  # noqa: E731
        self.cart_q, self.pole_q = (int(mj_model.jnt_qposadr[jnt(n)]) for n in (CART_JOINT, POLE_JOINT))
        self.cart_v, self.pole_v = (int(mj_model.jnt_dofadr[jnt(n)]) for n in (CART_JOINT, POLE_JOINT))
        self.cart_body, self.pole_body = (int(mj_model.jnt_bodyid[jnt(n)]) for n in (CART_JOINT, POLE_JOINT))

    def randomisable(self) -> tuple[str, ...]:
        """``cart_mass``, ``pole_mass``, ``pole_length`` (factors; the pole scales as a rod) on ``analytic`` and
        ``mjx``; Brax's pipelines: none."""
        return ("cart_mass", "pole_mass", "pole_length") if self.sim.backend in ("analytic", "mjx") else ()

    def sim_physics(self, domain: dict[str, jax.Array]) -> Any:
        """A drawn domain as the closed form's factors, or as MJX model fields (masses, the pole's inertia and
        centre of mass)."""
        one = jnp.ones((), jnp.float32)
        f = {name: domain.get(name, one) for name in ("cart_mass", "pole_mass", "pole_length")}
        if self.sim.backend == "analytic":
            return f
        m, c, p = self.sim.model, self.cart_body, self.pole_body
        mass = m.body_mass.at[c].multiply(f["cart_mass"]).at[p].multiply(f["pole_mass"])
        inertia = m.body_inertia.at[p].multiply(f["pole_mass"] * f["pole_length"] ** 2)
        return MjxEdit(model={"body_mass": mass, "body_inertia": inertia,
                              "body_ipos": m.body_ipos.at[p].multiply(f["pole_length"])}, data={})

    def init_pose(self, cart_x: jax.Array, pole_angle: jax.Array, cart_v: jax.Array = 0.0,
                  pole_vel: jax.Array = 0.0) -> tuple[jax.Array, jax.Array]:
        """``(qpos, qvel)`` for a cart position (m), pole angle (rad) and their rates."""
        qpos = jnp.zeros(2).at[self.cart_q].set(cart_x).at[self.pole_q].set(pole_angle)
        qvel = jnp.zeros(2).at[self.cart_v].set(cart_v).at[self.pole_v].set(pole_vel)
        return qpos, qvel

    def read_sensors(self, pipeline_state: Any) -> jax.Array:
        """The joint sensors: ``[cart_x (m), cart_v (m/s), pole_angle (rad), pole_angular_velocity (rad/s)]``."""
        q, v = self.sim.qpos(pipeline_state), self.sim.qvel(pipeline_state)
        return jnp.stack([q[self.cart_q], v[self.cart_v], q[self.pole_q], v[self.pole_v]])
