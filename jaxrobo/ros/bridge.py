"""What ROS carries for each task family: topics (from ``topics/<family>.yaml``), the readings the policy needs,
the observation built from them by the task's own native port (``envs/*/native.py``: the same numbers as in
training), the command message of an action, and the state messages the sim node publishes.

A reading is refused (:class:`Fault`, the node stops the robot) when it is missing, older than ``max_age`` against
the primary reading (the odometry, the joint states) or not finite."""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np
import yaml

from jaxrobo.core.config import ConfigError

HERE = os.path.dirname(os.path.abspath(__file__))
#: The task modules with a native port, and their family (the topic file's name).
FAMILIES = {"envs.quadcopter.goto": "quadcopter", "envs.quadcopter.goto_v2": "quadcopter",
            "envs.quadcopter.goto_twist": "quadcopter", "envs.cartpole.stay_up": "cartpole",
            "envs.cartpole.continuous": "cartpole"}
TOPIC_KEYS = {"quadcopter": ("cmd_vel", "takeoff", "land", "odom", "gt_pose", "gt_vel", "imu", "sonar_forward",
                             "sonar_left", "sonar_right", "sonar_down", "goal", "obstacles", "episode"),
              "cartpole": ("joint_states", "command", "episode")}
SONARS = ("sonar_forward", "sonar_left", "sonar_right", "sonar_down")


class Fault(Exception):
    """Why the policy cannot act now (a missing, stale or non-finite reading): stop the robot, say this.
    ``waiting``: the reading is missing or old, and may still come."""

    def __init__(self, why: str, waiting: bool = False):
        super().__init__(why)
        self.waiting = waiting


def ros_ids() -> list[str]:
    """The registered task ids with a ROS bridge: those whose class lives in a module of :data:`FAMILIES`."""
    from jaxrobo.task import registry

    def module(env_id):
        ep = registry.registration(env_id).entry_point
        return ep.partition(":")[0] if isinstance(ep, str) else ep.__module__

    return [i for i in registry.registered() if module(i) in FAMILIES]


def make_env(meta: dict, where: str = "policy.json") -> Any:
    """The task an export was trained on, with the run's options and parameters (``policy.json``'s ``env_id``,
    ``env_options``, ``env_params``)."""
    import jaxrobo

    env_id = meta.get("env_id")
    try:
        extra = {**dict(meta.get("env_options") or {}), **dict(meta.get("env_params") or {})}
        return jaxrobo.make(env_id, **extra)
    except (ConfigError, KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"{where}: env_id={env_id!r}: {err}") from None


def family(env: Any) -> str:
    fam = FAMILIES.get(type(env).__module__)
    if fam is None:
        name = env.spec.id if getattr(env, "spec", None) is not None else type(env).__name__
        raise ConfigError(f"{name}: no ROS bridge for this task (have: {', '.join(ros_ids())})")
    return fam


def load_topics(fam: str, path: str | None = None) -> dict:
    """The topic file of ``fam`` (default ``topics/<fam>.yaml``), checked field by field."""
    path = path or os.path.join(HERE, "topics", f"{fam}.yaml")
    try:
        with open(path) as f:
            cfg = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"{path}: cannot be read as YAML ({err})") from None
    if not isinstance(cfg, dict) or cfg.get("family") != fam:
        got = cfg.get("family") if isinstance(cfg, dict) else type(cfg).__name__
        raise ConfigError(f"{path}: family={got!r}, but the policy's task is a {fam} (topics/{fam}.yaml)")
    topics = cfg.get("topics")
    for key in TOPIC_KEYS[fam]:
        if not isinstance(topics, dict) or not isinstance(topics.get(key), str) or not topics[key].startswith("/"):
            raise ConfigError(f"{path}: topics.{key} must be a global topic name (a string starting with '/')")
    for key in ("max_age", "stale_after"):
        v = cfg.get(key)
        if v is not None and (not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 < v <= 60):
            raise ConfigError(f"{path}: {key}={v!r}: must be null or a number of seconds in (0, 60]")
    if fam == "cartpole":
        j = cfg.get("joints")
        if not isinstance(j, dict) or not all(isinstance(j.get(k), str) for k in ("cart", "pole")):
            raise ConfigError(f"{path}: joints.cart and joints.pole must be joint names")
    elif cfg.get("goal_param") is not None and not isinstance(cfg["goal_param"], str):
        raise ConfigError(f"{path}: goal_param must be null or a parameter name")
    return cfg


def _finite(topic: str, values) -> np.ndarray:
    a = np.asarray(values, np.float64)
    if not np.all(np.isfinite(a)):
        raise Fault(f"{topic}: non-finite value in the message ({a.tolist()})")
    return a


def stamp(msg) -> float:
    return msg.header.stamp.to_sec()


class Bridge:
    """Shared by both families: the port, the control period, the topics and the freshness rule."""

    family: str
    primary: str  # the reading that marks a moment (stamped; the policy acts on it)
    sensors: tuple  # the topics the policy node subscribes to
    command_topic: str

    def __init__(self, env: Any, cfg: dict, port: Any):
        self.env, self.cfg, self.port = env, cfg, port
        self.topics = cfg["topics"]
        self.period = float(port.n_substeps * port.model.opt.timestep)
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


class DroneBridge(Bridge):
    family, primary = "quadcopter", "odom"
    sensors = ("odom", *SONARS, "goal", "obstacles", "episode")  # what the policy node subscribes to
    command_topic = "cmd_vel"

    def __init__(self, env: Any, cfg: dict):
        from jaxrobo.task.registry import load_entry_point

        super().__init__(env, cfg, load_entry_point("envs.quadcopter.native:NativeGoto")(env))
        self.stamped = ("odom", *SONARS)  # one moment's readings; the goal keeps its episode's stamp
        self.needs = self.stamped + (() if cfg.get("goal_param") else ("goal",))

    def msg_types(self):
        from geometry_msgs.msg import PointStamped, Pose, Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import Imu, Range
        from std_msgs.msg import Empty, Float64MultiArray, Int32

        return {"cmd_vel": Twist, "takeoff": Empty, "land": Empty, "odom": Odometry, "gt_pose": Pose,
                "gt_vel": Twist, "imu": Imu, "goal": PointStamped, "obstacles": Float64MultiArray, "episode": Int32,
                **{s: Range for s in SONARS}}

    # ---- the policy's side --------------------------------------------------------------------------------
    def readings(self, latest: dict, goal=None) -> dict:
        t = self.fresh(latest, self.needs)
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

    def obstacles(self, msg) -> dict:
        rows = np.zeros((0, 7)) if msg is None or not msg.data else np.asarray(msg.data, np.float64)
        if rows.size % 7 or not np.all(np.isfinite(rows)):
            raise Fault(f"{self.topics['obstacles']}: expected finite rows of 7 numbers, got {rows.size} values")
        rows = rows.reshape(-1, 7)
        return {"kind": rows[:, 0].astype(np.int32), "center": rows[:, 1:4], "size": rows[:, 4:7],
                "active": np.ones(len(rows), bool)}

    def observation(self, latest: dict, goal=None) -> np.ndarray:
        r = self.readings(latest, goal)
        return self.port.observation(r["pos"], r["quat"], r["vz"], r["sonars"], r["goal"], r["obstacles"])

    def command_msg(self, action) -> Any:
        _, c = self.port.command(action)
        return self.twist(c)

    def zero_msg(self) -> Any:
        return self.twist(np.zeros(4))

    def twist(self, c) -> Any:
        from geometry_msgs.msg import Twist

        m = Twist()
        m.linear.x, m.linear.y, m.linear.z, m.angular.z = (float(x) for x in c)
        return m

    def reset_memory(self) -> None:
        pass  # the drone's command is a function of the action alone

    def outcome(self, readings: dict) -> tuple[bool, bool]:
        """``(arrived, failed)`` judged on the observed pose (the port's test on a copy of the readings)."""
        self.port.data.qpos[:3], self.port.data.qpos[3:7] = readings["pos"], readings["quat"]
        return self.port.outcome(readings["goal"], readings["obstacles"])

    # ---- the sim's side -------------------------------------------------------------------------------------
    def command_of(self, msg) -> np.ndarray:
        c = np.array([msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z], np.float64)
        return c if np.all(np.isfinite(c)) else np.zeros(4)

    def zero_command(self):
        return np.zeros(4)

    def advance(self, command) -> None:
        self.port.advance(lambda: self.port.controller(command))

    def task_of(self, task) -> dict:
        o = task.obstacles
        return {"goal": np.asarray(task.goal, np.float64),
                "obstacles": {"kind": np.asarray(o.kind), "center": np.asarray(o.center, np.float64),
                              "size": np.asarray(o.size, np.float64), "active": np.asarray(o.active)}}

    def episode_msgs(self, task: dict, t) -> dict:
        from geometry_msgs.msg import PointStamped
        from std_msgs.msg import Float64MultiArray

        g = PointStamped()
        g.header.stamp, g.header.frame_id = t, "world"
        g.point.x, g.point.y, g.point.z = (float(x) for x in task["goal"])
        o = task["obstacles"]
        act = np.asarray(o["active"], bool)
        rows = np.concatenate([np.asarray(o["kind"], np.float64)[act, None], o["center"][act], o["size"][act]], 1)
        return {"goal": g, "obstacles": Float64MultiArray(data=rows.reshape(-1).tolist())}

    def state_msgs(self, task: dict, t) -> dict:
        from geometry_msgs.msg import Pose, Twist
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import Imu, Range

        d = self.port.data
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = (float(x) for x in d.qpos[:3])
        w, x, y, z = (float(v) for v in d.qpos[3:7])
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = x, y, z, w
        vel = Twist()
        vel.linear.x, vel.linear.y, vel.linear.z = (float(v) for v in d.qvel[:3])
        vel.angular.x, vel.angular.y, vel.angular.z = (float(v) for v in d.qvel[3:6])
        odom = Odometry()
        odom.header.stamp, odom.header.frame_id, odom.child_frame_id = t, "world", "base_link"
        odom.pose.pose, odom.twist.twist = pose, vel
        imu = Imu()
        imu.header.stamp, imu.header.frame_id = t, "base_link"
        imu.orientation, imu.angular_velocity = pose.orientation, vel.angular
        out = {"odom": odom, "gt_pose": pose, "gt_vel": vel, "imu": imu}
        rng = self.port.p["sonar_range"]
        for name, value in zip(SONARS, self.port.sonars(task["obstacles"])):
            r = Range()
            r.header.stamp, r.header.frame_id = t, name
            r.radiation_type, r.field_of_view, r.min_range, r.max_range, r.range = 0, 0.0, 0.0, rng, float(value)
            out[name] = r
        return out

    def judge(self, task: dict, steps: int) -> tuple[bool, bool, float]:
        """``(done, success, episode reward)`` after ``steps``: arrival or failure ends it, as the horizon does;
        the reward is the outcome (1 on arrival)."""
        arrived, failed = self.port.outcome(task["goal"], task["obstacles"])
        return arrived or failed or steps >= self.port.horizon, arrived, float(arrived)


class CartPoleBridge(Bridge):
    family, primary = "cartpole", "joint_states"
    sensors = ("joint_states", "episode")
    command_topic = "command"

    def __init__(self, env: Any, cfg: dict):
        from jaxrobo.task.registry import load_entry_point

        super().__init__(env, cfg, load_entry_point("envs.cartpole.native:NativeCartPole")(env))
        self.needs = self.stamped = ("joint_states",)
        self.start = self._start_command(env)
        self.command = self.start

    @staticmethod
    def _start_command(env) -> float:
        """The cart command an episode starts from: the task's own reset (once, at start-up)."""
        import jax

        task = env.reset(jax.random.key(0)).task
        return float(np.asarray(getattr(task, "command", 0.0)))

    def msg_types(self):
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64, Int32

        return {"joint_states": JointState, "command": Float64, "episode": Int32}

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
        return self.port.observation(self.readings(latest)["joints"])

    def command_msg(self, action) -> Any:
        from std_msgs.msg import Float64

        _, self.command = self.port.command(action, self.command)
        return Float64(data=float(self.command))

    def zero_msg(self) -> Any:
        from std_msgs.msg import Float64

        return Float64(data=0.0)

    def reset_memory(self) -> None:
        self.command = self.start

    # ---- the sim's side -------------------------------------------------------------------------------------
    def command_of(self, msg) -> float:
        return float(msg.data) if math.isfinite(msg.data) else 0.0

    def zero_command(self):
        return self.start

    def advance(self, command) -> None:
        self.port.advance(command)

    def task_of(self, task) -> dict:
        return {"command": float(np.asarray(getattr(task, "command", 0.0)))}

    def episode_msgs(self, task: dict, t) -> dict:
        return {}

    def state_msgs(self, task: dict, t) -> dict:
        from sensor_msgs.msg import JointState

        j = self.port.joints()
        m = JointState()
        m.header.stamp = t
        m.name = [self.cfg["joints"]["cart"], self.cfg["joints"]["pole"]]
        m.position, m.velocity, m.effort = [float(j[0]), float(j[2])], [float(j[1]), float(j[3])], [0.0, 0.0]
        return {"joint_states": m}

    def judge(self, task: dict, steps: int) -> tuple[bool, bool, float]:
        """``(done, success, episode reward)``: the pole down or the cart out ends it, as the horizon does; the
        task's reward is 1 per step."""
        terminated = self.port.terminated(self.port.observe())
        return terminated or steps >= self.port.horizon, steps >= self.port.horizon and not terminated, float(steps)


def make_bridge(env: Any, topics_path: str | None = None) -> Bridge:
    fam = family(env)
    cfg = load_topics(fam, topics_path)
    return (DroneBridge if fam == "quadcopter" else CartPoleBridge)(env, cfg)
