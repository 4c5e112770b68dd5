"""Robots and tasks shipped with jaxrobo, one folder per robot family. Importing this package imports nothing else:
:func:`register_builtin` registers their ids (lazily: a task module, and MuJoCo with it, is imported only when its
env is made), called by :mod:`jaxrobo.task.registry` (through its ``BUILTIN_ENVS`` entry point) the first time an id
is looked up; a family's JAX-free modules (the native ports, the step functions they share with the tasks) import
without JAX.

Each family keeps its MJCF, robot, tasks, env YAML and fast kernels side by side::

    cartpole/     cartpole.xml  robot.py (CartPoleRobot)  dynamics.py (closed form: the XLA path's and the
                  Pallas chunk kernel's one source)  rules.py (the task's command and outcome per coordinate)
                  stay_up.py (CartPoleStayUp-v0, -LeftRight-v0)  kernel.py (a Q-learning chunk as one Pallas
                  kernel)  continuous.py (CartPoleContinuous-v0)  cartpole_stay_up.yaml
    quadcopter/   quadcopter.xml  robot.py (Quadcopter: Twist controller, sonar)  dynamics.py (controller and
                  rigid-body step per coordinate)  geometry.py (pose and ray tests per coordinate)  goto_step.py
                  (the Goto step per coordinate; these three are the hooks', the kernels' and native.py's one source,
                  over an array module)  rigid_body.py (closed form)  kernel.py (the control step as one Pallas
                  kernel)  live_show.py  goto.py  goto_v2.py  goto_kernel.py (the Goto step as one Pallas kernel)
                  goto_twist.py  native.py (native MuJoCo, no JAX)  quadcopter_*.yaml
    arm/          arm.xml  robot.py (ArmRobot)  reach.py (ArmReach-v0)  arm_reach.yaml

How to add your own robot or task (in this package or in your own module, docs/extending.md):

* a **robot** subclasses :class:`jaxrobo.api.Robot`: it loads its MJCF with :func:`jaxrobo.api.load_model`, builds
  its simulator with :func:`jaxrobo.api.make_simulator` (offering its hand-written backends,
  :class:`jaxrobo.api.ClosedFormSim` subclasses such as ``cartpole.dynamics.CartPoleSim`` and
  ``quadcopter.rigid_body.RigidBodySim``, by name), and adds its controller and sensors;
* a **task** subclasses :class:`jaxrobo.api.TaskEnv` with its ``Options``/``Params``, opens with its environment
  card, and is registered here with :func:`jaxrobo.api.register` (``"module:Class"``, its step limit, its YAML);
* a **continuous-action task** (``cartpole/continuous.py``: ``CartPoleContinuous-v0``; ``quadcopter/goto_twist.py``:
  ``QuadcopterGotoTwist-v0``) has a ``Box`` action space and an observation without discretisation, for Brax's PPO/SAC
  through :mod:`jaxrobo.interop.brax_env` (``jaxrobo train --agent ppo|sac``); it sits beside its discrete task, whose
  id stays exactly as it is.

A module here imports from jaxrobo only its public surface, :mod:`jaxrobo.api` (``tests/test_structure.py``
checks it): never the trainer, the CLI or a learner.
"""
from __future__ import annotations

import functools
import os

_HERE = os.path.dirname(os.path.abspath(__file__))
#: The robot families, each a folder of its own.
FAMILIES = ("cartpole", "quadcopter", "arm")


def asset_path(name: str) -> str:
    """Absolute path of a family's file by its name (``asset_path("cartpole.xml")`` is
    ``envs/cartpole/cartpole.xml``); an absolute path is returned as it is."""
    if os.path.isabs(name):
        return name
    for family in FAMILIES:
        path = os.path.join(_HERE, family, name)
        if os.path.exists(path):
            return path
    raise FileNotFoundError(f"{name!r} is in none of the robot families' folders ({', '.join(FAMILIES)})")


def _cfg(family: str, name: str) -> str:
    return os.path.join(_HERE, family, name)


@functools.cache
def register_builtin() -> None:
    """Register the shipped ids with :mod:`jaxrobo.task.registry` (once)."""
    from jaxrobo.api import deprecated_alias, register

    # Cart-pole (seed 001). Agent YAML names are relative to agents/configs/.
    register("CartPoleStayUp-v0", "envs.cartpole.stay_up:CartPoleStayUp",
             config=_cfg("cartpole", "cartpole_stay_up.yaml"), agent_config="cartpole_stay_up.yaml",
             description="seed 001: keep the pole up, 4 actions")
    # The seed's exercise 2.3 is a different task, not a newer CartPoleStayUp: an id of its own, so Gymnasium
    # never calls CartPoleStayUp-v0 "out of date". Its first name, CartPoleStayUp-v1, still works in jaxrobo.
    register("CartPoleStayUpLeftRight-v0", "envs.cartpole.stay_up:CartPoleStayUp",
             config=_cfg("cartpole", "cartpole_stay_up.yaml"), agent_config="cartpole_stay_up.yaml",
             description="seed exercise 2.3: left/right only", n_actions=2)
    deprecated_alias("CartPoleStayUp-v1", "CartPoleStayUpLeftRight-v0")
    # Quadcopter (seed 000): the faithful live-show task and the seed's homework (goto with obstacles).
    register("QuadcopterLiveShow-v0", "envs.quadcopter.live_show:QuadcopterLiveShow",
             config=_cfg("quadcopter", "quadcopter_live_show.yaml"), agent_config="quadcopter_live_show.yaml",
             description="seed 000: fly toward (14, 1, 0.7) observing x only (does not learn, as in the seed)")
    register("QuadcopterGoto-v1", "envs.quadcopter.goto:QuadcopterGoto",
             config=_cfg("quadcopter", "quadcopter_goto.yaml"), agent_config="quadcopter_goto.yaml",
             description="seed 000 homework: random goals, obstacles, sonar, discretised relative pose")
    register("QuadcopterGoto-v2", "envs.quadcopter.goto_v2:QuadcopterGoto2",
             config=_cfg("quadcopter", "quadcopter_goto_v2.yaml"), agent_config="quadcopter_goto_v2.yaml",
             description="Goto homework redesigned to learn: goal_clear feature, crash penalty 150, potential shaping")
    # Continuous actions (Box(-1, 1)) for Brax's PPO/SAC (jaxrobo.interop.brax_env): a task module each, beside its
    # discrete task, so the discrete ids stay exactly as they are.
    register("CartPoleContinuous-v0", "envs.cartpole.continuous:CartPoleContinuous",
             description="keep the pole up with a continuous force on the cart (Box(-1, 1) x 10 N)")
    register("QuadcopterGotoTwist-v0", "envs.quadcopter.goto_twist:QuadcopterGotoTwist",
             description="Goto with a continuous Twist [vx, vy, vz, yaw_rate] bounded by speed_value")
    # Planar two-joint arm (openai_ros' reach tasks): two position servos, a random goal each episode.
    register("ArmReach-v0", "envs.arm.reach:ArmReach",
             config=_cfg("arm", "arm_reach.yaml"), agent_config="arm_reach.yaml",
             description="planar 2-joint arm under position control: reach a random goal, 4 actions")

