"""Robots and tasks shipped with jaxrobo; importing this package registers their ids (lazily: a task module,
and MuJoCo with it, is imported only when its env is made). :mod:`jaxrobo.registry` imports it by name (its
``BUILTIN_ENVS`` entry point) the first time an id is looked up.

Layout, and how to add your own robot or task (in this package or in your own):

* a **robot** (``cartpole.py``, ``quadcopter.py``) subclasses :class:`jaxrobo.robot.Robot`: it loads its MJCF
  with :func:`jaxrobo.sim.load_model` from :func:`asset_path` (or any path of its own), builds its simulator with
  :func:`jaxrobo.sim.make_simulator` (offering its hand-written backends, :class:`jaxrobo.sim.ClosedFormSim`
  subclasses such as ``cartpole_dynamics.CartPoleSim`` and ``rigid_body.RigidBodySim``, by name), and adds its
  controller and sensors;
* a **task** (``cartpole_stay_up.py``, ``quadcopter_goto.py``, ``quadcopter_live_show.py``) subclasses
  :class:`jaxrobo.env.TaskEnv` with its ``Options``/``Params`` and is registered here with
  :func:`jaxrobo.registry.register` (``"module:Class"``, its step limit, its YAML files under ``configs/``);
* a **continuous-action task** (``cartpole_continuous.py``: ``CartPoleContinuous-v0``, a bounded force on the
  cart; ``quadcopter_goto_twist.py``: ``QuadcopterGotoTwist-v0``, the Goto task flown with a Twist
  ``[vx, vy, vz, yaw_rate]`` bounded by ``speed_value``) has a ``Box`` action space and an observation without
  discretisation, for Brax's PPO/SAC through :mod:`jaxrobo.brax_env` (``jaxrobo train --agent ppo|sac``); it sits
  beside its discrete task, whose id stays exactly as it is.

What a module here may import from jaxrobo is the task API: ``jaxrobo.env``, ``jaxrobo.robot``, ``jaxrobo.sim``,
``jaxrobo.spaces``, ``jaxrobo.struct``, ``jaxrobo.rng``, ``jaxrobo.registry`` and the rollout/evaluation module
``jaxrobo.rollout`` (for a task's own evaluation); never the trainer, the CLI or a learner
(``tests/test_structure.py`` checks it).
"""
from __future__ import annotations

import os

from jaxrobo.registry import deprecated_alias, register

_CONFIGS = os.path.join(os.path.dirname(__file__), "configs")
#: The robots' MJCF files.
ASSETS = os.path.join(os.path.dirname(__file__), "assets")


def asset_path(*parts: str) -> str:
    """Absolute path of a file in ``envs/assets``."""
    return os.path.join(ASSETS, *parts)


def _cfg(name: str) -> str:
    return os.path.join(_CONFIGS, name)


def _register_builtin() -> None:
    # Cart-pole (seed 001). Agent YAML names are relative to agents/configs/.
    register("CartPoleStayUp-v0", "envs.cartpole_stay_up:CartPoleStayUp",
             config=_cfg("cartpole_stay_up.yaml"), agent_config="cartpole_stay_up.yaml",
             description="seed 001: keep the pole up, 4 actions")
    # The seed's exercise 2.3 is a different task, not a newer CartPoleStayUp: an id of its own, so Gymnasium
    # never calls CartPoleStayUp-v0 "out of date". Its first name, CartPoleStayUp-v1, still works in jaxrobo.
    register("CartPoleStayUpLeftRight-v0", "envs.cartpole_stay_up:CartPoleStayUp",
             config=_cfg("cartpole_stay_up.yaml"), agent_config="cartpole_stay_up.yaml",
             description="seed exercise 2.3: left/right only", n_actions=2)
    deprecated_alias("CartPoleStayUp-v1", "CartPoleStayUpLeftRight-v0")
    # Quadcopter (seed 000): the faithful live-show task and the seed's homework (goto with obstacles).
    register("QuadcopterLiveShow-v0", "envs.quadcopter_live_show:QuadcopterLiveShow",
             config=_cfg("quadcopter_live_show.yaml"), agent_config="quadcopter_live_show.yaml",
             description="seed 000: fly toward (14, 1, 0.7) observing x only (does not learn, as in the seed)")
    register("QuadcopterGoto-v1", "envs.quadcopter_goto:QuadcopterGoto",
             config=_cfg("quadcopter_goto.yaml"), agent_config="quadcopter_goto.yaml",
             description="seed 000 homework: random goals, obstacles, sonar, discretised relative pose")
    register("QuadcopterGoto-v2", "envs.quadcopter_goto2:QuadcopterGoto2",
             config=_cfg("quadcopter_goto_v2.yaml"), agent_config="quadcopter_goto_v2.yaml",
             description="Goto homework redesigned to learn: goal_clear feature, crash penalty 150, potential shaping")
    # Continuous actions (Box(-1, 1)) for Brax's PPO/SAC (jaxrobo.brax_env): a task module each, beside its
    # discrete task, so the discrete ids stay exactly as they are.
    register("CartPoleContinuous-v0", "envs.cartpole_continuous:CartPoleContinuous",
             description="keep the pole up with a continuous force on the cart (Box(-1, 1) x 10 N)")
    register("QuadcopterGotoTwist-v0", "envs.quadcopter_goto_twist:QuadcopterGotoTwist",
             description="Goto with a continuous Twist [vx, vy, vz, yaw_rate] bounded by speed_value")
    # Planar two-joint arm (openai_ros' reach tasks): two position servos, a random goal each episode.
    register("ArmReach-v0", "envs.arm_reach:ArmReach",
             config=_cfg("arm_reach.yaml"), agent_config="arm_reach.yaml",
             description="planar 2-joint arm under position control: reach a random goal, 4 actions")


_register_builtin()
