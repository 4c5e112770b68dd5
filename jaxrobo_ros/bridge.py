"""What ROS carries for each task family, on the robot's side: topics (from ``topics/<family>.yaml``), the readings
the policy needs, the observation built from them and the command message of an action (by the export's own
``robot`` section: :class:`numpy_policy.QuadcopterIO` / :class:`numpy_policy.CartPoleIO`, the same code the native
ports compute with). numpy, yaml and the ROS message packages only: no JAX, no task module, no MuJoCo.

A reading is refused (:class:`Fault`, the node stops the robot) when it is missing, older than ``max_age`` against
the primary reading (the odometry, the joint states) or not finite.

Each command also goes out stamped, on ``command_stamped`` (default: the command topic's name + ``_stamped``): the
same command with the stamp of the state it answers (``geometry_msgs/TwistStamped`` for the drone,
``sensor_msgs/JointState`` with the cart joint's velocity for the cart-pole). The command topics themselves
(``std_msgs/Float64``, ``geometry_msgs/Twist``) carry no stamp; the lockstep sim steps on the stamped copy, so it can
tell an answer to the state it waits on from a late or repeated answer to a state it has already stepped. The policy
node also names in the copy's ``header.frame_id`` the episode whose start it had heard of when it acted
(:func:`episode_tag`, from ``/jaxrobo/episode``; the cart-pole's accumulated command starts afresh there): that topic
and the states travel over separate connections, so a new episode's first state can arrive before its number, and the
lockstep sim does not step on an answer tagged with another episode than its own (it republishes the state, which the
node then answers afresh).

The drone's goal and obstacles race the same way: the sim publishes a new episode's goal and obstacles before its
first state, over connections of their own. ``/jaxrobo/episode`` is a ``std_msgs/Header`` (:func:`episode_msg`:
``seq`` the episode's number, ``stamp`` its start, the stamp of its first state and of its goal), so the goal, in
frame ``world`` as a tf or RViz consumer needs, is matched to its episode by its stamp; the obstacle array, which has
no header, names its episode in ``layout.dim[0].label`` (:func:`episode_tag`). :meth:`DroneBridge.readings` takes
them only in the episode of the last ``/jaxrobo/episode`` (:meth:`Bridge.episode_check`: a goal heard with no episode
number, from Gazebo or a robot, and obstacles naming none count as current): the policy node and the Gymnasium env
over ROS wait for them (:class:`Fault`, ``waiting``) instead of acting on a new state with the last episode's
goal."""
from __future__ import annotations

import os
from typing import Any

import numpy as np
import yaml

from jaxrobo_ros.system import SetupError

HERE = os.path.dirname(os.path.abspath(__file__))
TOPIC_KEYS = {"quadcopter": ("cmd_vel", "takeoff", "land", "odom", "gt_pose", "gt_vel", "imu", "sonar_forward",
                             "sonar_left", "sonar_right", "sonar_down", "goal", "obstacles", "episode"),
              "cartpole": ("joint_states", "command", "episode")}
SONARS = ("sonar_forward", "sonar_left", "sonar_right", "sonar_down")
#: The command's topic key of each family (``topics.command_stamped`` defaults to its name + ``_stamped``).
COMMAND_KEYS = {"quadcopter": "cmd_vel", "cartpole": "command"}


#: The episode a message belongs to, in its ``header.frame_id`` (a stamped command copy: the episode it was computed
#: in, the node's last ``/jaxrobo/episode``) or, for an array (the obstacles), its ``layout.dim[0].label``. Not the
#: goal's: its frame_id is its frame, and its stamp (its episode's start) names its episode.
EPISODE_TAG = "jaxrobo_episode "
#: The frame of the drone's goal, odometry and episode messages.
WORLD = "world"


def episode_tag(episode: int) -> str:
    return f"{EPISODE_TAG}{int(episode)}"


def episode_msg(episode: int, start) -> Any:
    """What the sim publishes on ``/jaxrobo/episode`` when episode ``episode`` starts: a ``std_msgs/Header`` with
    ``seq`` its number and ``stamp`` its start (``start``, a ``rospy.Time``: its first state's and its goal's).
    rospy sets the ``seq`` of a message that has a header, not of a Header itself (``rospy.msg.serialize_message``),
    so the number arrives as sent."""
    from std_msgs.msg import Header

    return Header(seq=int(episode), stamp=start, frame_id=WORLD)


def tagged_episode(msg) -> int | None:
    """The episode ``msg`` names (:func:`episode_tag`: a header's ``frame_id``, an array's first dimension's label);
    None where it names none (a sender that does not tag, or the policy node before any ``/jaxrobo/episode``
    reached it)."""
    if hasattr(msg, "header"):
        frame = getattr(msg.header, "frame_id", "") or ""
    else:
        dims = getattr(getattr(msg, "layout", None), "dim", None) or ()
        frame = (getattr(dims[0], "label", "") or "") if dims else ""
    if not frame.startswith(EPISODE_TAG):
        return None
    try:
        return int(frame[len(EPISODE_TAG):])
    except ValueError:
        return None


class Fault(Exception):
    """Why the policy cannot act now (a missing, stale or non-finite reading): stop the robot, say this.
    ``waiting``: the reading is missing or old, and may still come."""

    def __init__(self, why: str, waiting: bool = False):
        super().__init__(why)
        self.waiting = waiting


def load_topics(fam: str, path: str | None = None) -> dict:
    """The topic file of ``fam`` (default ``topics/<fam>.yaml``), checked field by field."""
    path = path or os.path.join(HERE, "topics", f"{fam}.yaml")
    try:
        with open(path) as f:
            cfg = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as err:
        raise SetupError(f"{path}: cannot be read as YAML ({err})") from None
    if not isinstance(cfg, dict) or cfg.get("family") != fam:
        got = cfg.get("family") if isinstance(cfg, dict) else type(cfg).__name__
        raise SetupError(f"{path}: family={got!r}, but the policy's task is a {fam} (topics/{fam}.yaml)")
    topics = cfg.get("topics")
    for key in TOPIC_KEYS[fam] + ("command_stamped",):
        if key == "command_stamped" and topics.get(key) is None:  # optional: topic files without it keep working
            topics[key] = topics[COMMAND_KEYS[fam]] + "_stamped"
        if not isinstance(topics, dict) or not isinstance(topics.get(key), str) or not topics[key].startswith("/"):
            raise SetupError(f"{path}: topics.{key} must be a global topic name (a string starting with '/')")
    for key in ("max_age", "stale_after"):
        v = cfg.get(key)
        if v is not None and (not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 < v <= 60):
            raise SetupError(f"{path}: {key}={v!r}: must be null or a number of seconds in (0, 60]")
    if fam == "cartpole":
        j = cfg.get("joints")
        if not isinstance(j, dict) or not all(isinstance(j.get(k), str) for k in ("cart", "pole")):
            raise SetupError(f"{path}: joints.cart and joints.pole must be joint names")
    elif cfg.get("goal_param") is not None and not isinstance(cfg["goal_param"], str):
        raise SetupError(f"{path}: goal_param must be null or a parameter name")
    return cfg


def _finite(topic: str, values) -> np.ndarray:
    a = np.asarray(values, np.float64)
    if not np.all(np.isfinite(a)):
        raise Fault(f"{topic}: non-finite value in the message ({a.tolist()})")
    return a


def stamp(msg) -> float:
    return msg.header.stamp.to_sec()


class Bridge:
    """Shared by both families: the task's robot side (``io``), the control period, the topics and the freshness
    rule."""

    family: str
    primary: str  # the reading that marks a moment (stamped; the policy acts on it)
    sensors: tuple  # the topics the policy node subscribes to
    command_topic: str
    stamped: tuple  # one moment's readings

    def __init__(self, io: Any, cfg: dict):
        self.io, self.cfg = io, cfg
        self.topics = cfg["topics"]
        self.period = float(io.period)
        self.max_age = float(cfg.get("max_age") or 0.5 * self.period)
        self.stale_after = float(cfg.get("stale_after") or 1.0)

    def fresh(self, latest: dict, names) -> float:
        """The primary reading's stamp once every reading in ``names`` is there and within ``max_age`` of it."""
        t = stamp(latest[self.primary]) if self.primary in latest else None
        for name in names:
            if name not in latest:
                raise Fault(f"{self.topics[name]}: no message yet", waiting=True)
            if t is not None and name in self.stamped and abs(stamp(latest[name]) - t) > self.max_age:
                raise Fault(f"{self.topics[name]}: stamp {stamp(latest[name]):.3f} s is more than {self.max_age:g} "
                            f"s from {self.topics[self.primary]}'s {t:.3f} s (stale)", waiting=True)
        return t

    @staticmethod
    def episode_check(msg, episode) -> bool:
        """Whether ``msg`` (the drone's goal or obstacles) belongs to ``episode`` (the last ``/jaxrobo/episode``
        heard, :func:`episode_msg`; None: none yet). The goal: where an episode was heard, iff stamped with its
        start (the sim stamps each goal so); where none was (Gazebo, a robot: nothing numbers episodes), it is
        current. The obstacles: one naming no episode (:func:`tagged_episode`: an older sim, Gazebo, a robot)
        belongs to any; one naming one, to that one alone (the number of a new episode may still be on its way)."""
        if hasattr(msg, "header"):
            return episode is None or msg.header.stamp == episode.stamp
        tag = tagged_episode(msg)
        return tag is None or (episode is not None and tag == episode.seq)

    @staticmethod
    def episode_of(latest: dict) -> int | None:
        """The episode of the readings ``latest``: its last ``/jaxrobo/episode``'s number; None where none was
        heard."""
        m = latest.get("episode")
        return None if m is None else int(m.seq)

    def stamped_type(self) -> Any:
        """The message type of ``command_stamped``."""
        raise NotImplementedError

    def stamped_command(self, out: Any, when: Any) -> Any:
        """The command message ``out`` again, stamped ``when`` (the ``rospy.Time`` of the primary reading it
        answers), for ``command_stamped``."""
        raise NotImplementedError


class DroneBridge(Bridge):
    family, primary = "quadcopter", "odom"
    sensors = ("odom", *SONARS, "goal", "obstacles", "episode")  # what the policy node subscribes to
    command_topic = "cmd_vel"
    stamped = ("odom", *SONARS)  # the goal keeps its episode's stamp

    def __init__(self, io: Any, cfg: dict):
        super().__init__(io, cfg)
        self.needs = self.stamped + (() if cfg.get("goal_param") else ("goal",))

    def msg_types(self):
        from geometry_msgs.msg import PointStamped, Pose, Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import Imu, Range
        from std_msgs.msg import Empty, Float64MultiArray, Header

        return {"cmd_vel": Twist, "takeoff": Empty, "land": Empty, "odom": Odometry, "gt_pose": Pose,
                "gt_vel": Twist, "imu": Imu, "goal": PointStamped, "obstacles": Float64MultiArray, "episode": Header,
                **{s: Range for s in SONARS}}

    def readings(self, latest: dict, goal=None) -> dict:
        t = self.fresh(latest, self.needs)
        self.current(latest, goal is None)
        o = latest["odom"]
        p, q, v = o.pose.pose.position, o.pose.pose.orientation, o.twist.twist.linear
        top = self.topics
        pos = _finite(top["odom"], [p.x, p.y, p.z])
        quat = _finite(top["odom"], [q.w, q.x, q.y, q.z])
        vz = float(_finite(top["odom"], [v.z])[0])
        sonars = [float(_finite(top[s], [latest[s].range])[0]) for s in SONARS]
        if goal is None:
            g = latest["goal"].point
            goal = _finite(top["goal"], [g.x, g.y, g.z])
        obstacles = self.obstacles(latest.get("obstacles"))
        return {"t": t, "pos": pos, "quat": quat, "vz": vz, "sonars": sonars, "goal": np.asarray(goal, np.float64),
                "obstacles": obstacles}

    def current(self, latest: dict, goal_topic: bool = True) -> None:
        """:class:`Fault` (``waiting``) unless the goal (``goal_topic``: from its topic, not a parameter) and the
        obstacles in ``latest`` are those of its episode (:meth:`episode_check`). A sim that numbers its episodes
        publishes each one's obstacles with its goal: then the obstacles must be there."""
        ep = latest.get("episode")
        heard = "none heard yet" if ep is None else f"episode {ep.seq}, started at {ep.stamp.to_sec():.3f} s"
        goal = latest.get("goal") if goal_topic else None
        for name, msg in (("goal", goal), ("obstacles", latest.get("obstacles"))):
            if msg is None:
                if name == "obstacles" and goal is not None and ep is not None:
                    raise Fault(f"{self.topics[name]}: no message yet for episode {ep.seq}", waiting=True)
            elif not self.episode_check(msg, ep):
                what = f"stamped {stamp(msg):.3f} s" if name == "goal" else f"of episode {tagged_episode(msg)}"
                raise Fault(f"{self.topics[name]}: {what}, not of the current episode ({heard} on "
                            f"{self.topics['episode']})", waiting=True)

    def obstacles(self, msg) -> dict:
        rows = np.zeros((0, 7)) if msg is None or not msg.data else np.asarray(msg.data, np.float64)
        if rows.size % 7 or not np.all(np.isfinite(rows)):
            raise Fault(f"{self.topics['obstacles']}: expected finite rows of 7 numbers, got {rows.size} values")
        rows = rows.reshape(-1, 7)
        return {"kind": rows[:, 0].astype(np.int32), "center": rows[:, 1:4], "size": rows[:, 4:7],
                "active": np.ones(len(rows), bool)}

    def observation(self, latest: dict, goal=None) -> np.ndarray:
        r = self.readings(latest, goal)
        return self.io.observation(r["pos"], r["quat"], r["vz"], r["sonars"], r["goal"], r["obstacles"])

    def command_msg(self, action) -> Any:
        _, c = self.io.command(action)
        return self.twist(c)

    def zero_msg(self) -> Any:
        return self.twist(np.zeros(4))

    def stamped_type(self) -> Any:
        from geometry_msgs.msg import TwistStamped

        return TwistStamped

    def stamped_command(self, out: Any, when: Any) -> Any:
        from geometry_msgs.msg import TwistStamped

        m = TwistStamped(twist=out)
        m.header.stamp = when
        return m

    def twist(self, c) -> Any:
        from geometry_msgs.msg import Twist

        m = Twist()
        m.linear.x, m.linear.y, m.linear.z, m.angular.z = (float(x) for x in c)
        return m

    def reset_memory(self) -> None:
        pass  # the drone's command is a function of the action alone


class CartPoleBridge(Bridge):
    family, primary = "cartpole", "joint_states"
    sensors = ("joint_states", "episode")
    command_topic = "command"
    stamped = ("joint_states",)

    def __init__(self, io: Any, cfg: dict):
        super().__init__(io, cfg)
        self.needs = self.stamped
        self.start = float(io.start)  # the cart command an episode starts from (the task's reset)
        self.command = self.start

    def msg_types(self):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, Header

        return {"joint_states": JointState, "command": Float64, "episode": Header}

    def joints(self, msg) -> np.ndarray:
        names = list(msg.name)
        top = self.topics["joint_states"]
        out = []
        for key in ("cart", "pole"):
            name = self.cfg["joints"][key]
            if name not in names:
                raise Fault(f"{top}: no joint {name!r} (joints: {names})")
            i = names.index(name)
            if i >= len(msg.position) or i >= len(msg.velocity):
                raise Fault(f"{top}: joint {name!r} has no position or velocity")
            out += [msg.position[i], msg.velocity[i]]
        return _finite(top, out)

    def readings(self, latest: dict, goal=None) -> dict:
        t = self.fresh(latest, self.needs)
        return {"t": t, "joints": self.joints(latest["joint_states"])}

    def observation(self, latest: dict, goal=None) -> np.ndarray:
        return self.io.observation(self.readings(latest)["joints"])

    def command_msg(self, action) -> Any:
        from std_msgs.msg import Float64

        _, self.command = self.io.command(action, self.command)
        return Float64(data=float(self.command))

    def zero_msg(self) -> Any:
        from std_msgs.msg import Float64

        return Float64(data=0.0)

    def stamped_type(self) -> Any:
        from sensor_msgs.msg import JointState

        return JointState

    def stamped_command(self, out: Any, when: Any) -> Any:
        from sensor_msgs.msg import JointState

        m = JointState(name=[self.cfg["joints"]["cart"]], velocity=[float(out.data)])
        m.header.stamp = when
        return m

    def reset_memory(self) -> None:
        self.command = self.start


#: The robot side of each family.
BRIDGES = {b.family: b for b in (DroneBridge, CartPoleBridge)}


def make_bridge(io: Any, topics_path: str | None = None) -> Bridge:
    """The robot-side bridge of a task's ``io`` (an export's ``policy.io``) on the family's topics."""
    return BRIDGES[io.family](io, load_topics(io.family, topics_path))
