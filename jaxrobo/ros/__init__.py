"""jaxrobo and ROS 1, the side that needs the task: a native-MuJoCo stand-in for Gazebo (the sim node), a Gymnasium
env over live topics, ``jaxrobo ros up`` (docs/ros.md). The trained policy as a rospy node is the robot's side,
:mod:`jaxrobo_ros` (no JAX).

rospy is not on PyPI: it comes from the system's packages (Debian: ``apt-get install ros-core python3-rospy ...``)
and lives under the system Python's ``dist-packages``. :func:`rospy` imports it; where it is not importable from
jaxrobo's interpreter (a virtual environment) but the system directory holds it, that directory is appended to
``sys.path`` (appended, so the environment's own packages keep precedence), and only then.
"""
from __future__ import annotations

from jaxrobo_ros.system import INSTALL, RosUnavailable, rospy, unavailable_reason

__all__ = ["INSTALL", "RosUnavailable", "rospy", "unavailable_reason"]


def _register_gymnasium() -> None:
    """``gym.make("jaxrobo-ros/<id>")`` once ``jaxrobo.ros`` is imported (nothing ROS is imported until then)."""
    from jaxrobo.ros import gym_env

    gym_env.register()


_register_gymnasium()
