"""Where ROS 1 comes from: rospy is not on PyPI but in the system's packages (Debian: ``apt-get install ros-core
python3-rospy ...``), under the system Python's ``dist-packages``. :func:`rospy` imports it; where it is not importable
from jaxrobo's interpreter (a virtual environment) but the system directory holds it, that directory is appended to
``sys.path`` (appended, so the environment's own packages keep precedence), and only then."""
from __future__ import annotations

import importlib
import os
import sys

#: Where Debian's python3-rospy installs rospy (the system Python's packages).
SYSTEM_PACKAGES = "/usr/lib/python3/dist-packages"
#: How to get ROS 1 where it is missing: one line for error messages.
INSTALL = ("ROS 1 (rospy) is not importable; on Debian/Ubuntu: apt-get install ros-core python3-rospy "
           "python3-std-msgs python3-geometry-msgs python3-nav-msgs python3-sensor-msgs python3-rosgraph-msgs "
           "python3-genpy (docs/ros.md)")


class RosUnavailable(RuntimeError):
    """rospy (or a message package) cannot be imported; the message says how to install it."""


class SetupError(ValueError):
    """An export, topic file or parameter the node cannot work with: one line saying which and why; nothing is
    started (the commands exit with 2)."""


def rospy():
    """The ``rospy`` module, importing the system's copy where the running interpreter has none."""
    try:
        return importlib.import_module("rospy")
    except ImportError:
        pass
    if os.path.isdir(os.path.join(SYSTEM_PACKAGES, "rospy")) and SYSTEM_PACKAGES not in sys.path:
        sys.path.append(SYSTEM_PACKAGES)
        try:
            return importlib.import_module("rospy")
        except ImportError as err:
            raise RosUnavailable(f"{INSTALL} ({SYSTEM_PACKAGES}/rospy fails to import: {err})") from None
    raise RosUnavailable(INSTALL)


def line_buffered() -> None:
    """Each line a node writes reaches its log file when it is written: rospy's INFO lines go to stdout without a
    flush, and Python buffers stdout in blocks when it is a file (roslaunch's ``output="log"``, a node started with
    its output redirected), so a line such as "acting again" would show only at exit."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.reconfigure(line_buffering=True)
        except (AttributeError, ValueError, OSError):  # a stream that is not a text file (a test's capture)
            pass


def stop_on_signals() -> list[int]:
    """A list that SIGINT and SIGTERM append their number to: a node's main loop runs while it is empty. The
    handler only appends: Python runs it in the main thread between bytecodes, where that thread may hold a lock
    (an Event's own, inside ``Event.wait``), so a handler that takes one (``Event.set``) can deadlock the node: it
    then never stops the robot or writes what it writes at exit, and is killed."""
    import signal

    stopping: list[int] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stopping.append(signum))
    return stopping


def split_ros_args(argv) -> tuple[list[str], list[str]]:
    """``(argv without ROS's own arguments, those arguments)``: the ``name:=value`` arguments roslaunch and rosrun
    give a node (remappings ``from:=to``, ``__name:=``, ``__ns:=``, ``__log:=``, private parameters ``_p:=v``), told
    apart by ``rospy.myargv``; the nodes hand them to ``rospy.init_node``. Where rospy does not import nothing is
    split (the command then says how to install ROS)."""
    argv = list(argv)
    try:
        plain = rospy().myargv(argv)
    except RosUnavailable:
        return argv, []
    keep = set(plain)
    return plain, [a for a in argv if a not in keep]


def unavailable_reason() -> str | None:
    """None where rospy and the message packages import; else why not (the install line)."""
    try:
        rospy()
        for name in ("std_msgs.msg", "geometry_msgs.msg", "sensor_msgs.msg", "nav_msgs.msg", "rosgraph_msgs.msg",
                     "genpy"):
            importlib.import_module(name)
    except (RosUnavailable, ImportError) as err:
        return str(err) if isinstance(err, RosUnavailable) else f"{INSTALL} ({err})"
    return None
