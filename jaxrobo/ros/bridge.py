"""The simulator's side of what ROS carries (the sim node and the Gymnasium env over ROS; they need the task): the
task's native port (``envs/*/native.py``) behind the robot-side bridges of :mod:`jaxrobo_ros.bridge`, plus the state
messages the sim publishes, the command it takes and the outcome it judges. :func:`robot_section` is what
``jaxrobo export`` writes into ``policy.json`` for the policy node (the port's constants)."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxrobo.core.config import ConfigError
from jaxrobo_ros.bridge import SONARS, WORLD, CartPoleBridge, DroneBridge, episode_tag, load_topics

#: The task modules with a native port: their family (the topic file's name) and the port's entry point.
FAMILIES = {"envs.quadcopter.goto": "quadcopter", "envs.quadcopter.goto_v2": "quadcopter",
            "envs.quadcopter.goto_twist": "quadcopter", "envs.cartpole.stay_up": "cartpole",
            "envs.cartpole.continuous": "cartpole"}
PORTS = {"quadcopter": "envs.quadcopter.native:NativeGoto", "cartpole": "envs.cartpole.native:NativeCartPole"}


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


def native_port(env: Any) -> Any:
    """The task's native port, with the task's own constants (the cart-pole's start command from its reset)."""
    from jaxrobo.task.registry import load_entry_point

    fam = family(env)
    port = load_entry_point(PORTS[fam])
    return port(env, start_command=_start_command(env)) if fam == "cartpole" else port(env)


def _start_command(env) -> float:
    """The cart command an episode starts from: the task's own reset."""
    import jax

    task = env.reset(jax.random.key(0)).task
    return float(np.asarray(getattr(task, "command", 0.0)))


def robot_section(meta: dict) -> dict | None:
    """``policy.json``'s ``robot`` section for an export of ``meta`` (its ``env_id``, options and parameters): the
    native port's constants (control period, observation constants, action table); None for a task without a
    port."""
    if meta.get("env_id") not in ros_ids():  # before building it: a task without a port needs nothing here
        return None
    return native_port(make_env(meta)).robot_section()


class DroneSim(DroneBridge):
    """The drone's topics on the simulator's side: the port's state messages, the commanded Twist, the outcome."""

    def __init__(self, env: Any, cfg: dict, port: Any):
        super().__init__(port.io, cfg)
        self.env, self.port = env, port

    def observed(self, readings: dict) -> None:
        """Put the observed pose into the port: :meth:`score` judges the drone the readings show, not the port's
        own."""
        self.port.data.qpos[:3], self.port.data.qpos[3:7] = readings["pos"], readings["quat"]

    # ---- the sim's side -------------------------------------------------------------------------------------
    def command_of(self, msg) -> np.ndarray:
        c = np.array([msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z], np.float64)
        return c if np.all(np.isfinite(c)) else np.zeros(4)

    def command_of_stamped(self, msg) -> np.ndarray:
        """The command of ``command_stamped``'s TwistStamped (:meth:`DroneBridge.stamped_command`)."""
        return self.command_of(msg.twist)

    def zero_command(self):
        return np.zeros(4)

    def advance(self, command) -> None:
        self.port.advance(lambda: self.port.controller(command))

    def task_of(self, task) -> dict:
        o = task.obstacles
        return {"goal": np.asarray(task.goal, np.float64),
                "obstacles": {"kind": np.asarray(o.kind), "center": np.asarray(o.center, np.float64),
                              "size": np.asarray(o.size, np.float64), "active": np.asarray(o.active)},
                "potentials": self.port.potentials(task), "return": 0.0}

    def task_seen(self, readings: dict, obs: np.ndarray) -> dict:
        """An episode as its first readings show it, for a client of the topics (it has no task variables): the
        goal and obstacles its topics carry, and the reward's potentials read off its first observation."""
        return {"goal": readings["goal"], "obstacles": readings["obstacles"],
                "potentials": self.port.potentials_of(obs), "return": 0.0}

    def episode_msgs(self, task: dict, t, episode: int) -> dict:
        """Episode ``episode``'s goal (world frame, stamped ``t``: its first state's, the episode's start that
        ``/jaxrobo/episode`` carries) and obstacles (naming the episode in ``layout.dim[0].label``,
        :func:`jaxrobo_ros.bridge.episode_tag`), so that a subscriber does not take them for another episode's
        (:meth:`jaxrobo_ros.bridge.Bridge.episode_check`)."""
        from geometry_msgs.msg import PointStamped
        from std_msgs.msg import Float64MultiArray, MultiArrayDimension

        g = PointStamped()
        g.header.stamp, g.header.frame_id = t, WORLD
        g.point.x, g.point.y, g.point.z = (float(x) for x in task["goal"])
        o = task["obstacles"]
        act = np.asarray(o["active"], bool)
        rows = np.concatenate([np.asarray(o["kind"], np.float64)[act, None], o["center"][act], o["size"][act]], 1)
        m = Float64MultiArray(data=rows.reshape(-1).tolist())
        m.layout.dim = [MultiArrayDimension(label=episode_tag(episode), size=len(rows), stride=rows.size),
                        MultiArrayDimension(label="kind cx cy cz sx sy sz", size=7, stride=7)]
        return {"goal": g, "obstacles": m}

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
        odom.header.stamp, odom.header.frame_id, odom.child_frame_id = t, WORLD, "base_link"
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

    def score(self, task: dict, obs: np.ndarray) -> tuple[bool, bool, float]:
        """``(arrived, failed, reward)`` of the step that left the drone where the port holds it, observed as
        ``obs``: the task's outcome and its shaped reward (:meth:`envs.quadcopter.native.NativeGoto.reward`), the
        potentials and the episode's return in ``task`` carried on. The sim node sums these for ``/openai/reward``,
        the Gymnasium env over ROS returns each one."""
        arrived, failed = self.port.outcome(task["goal"], task["obstacles"])
        r, task["potentials"] = self.port.reward(obs, task["potentials"], arrived, failed)
        task["return"] += r
        return arrived, failed, r

    def judge(self, task: dict, steps: int) -> tuple[bool, bool, float]:
        """``(done, success, episode reward)`` after ``steps``: arrival or failure ends it, as the horizon does;
        the reward is the task's own (its shaped per-step reward, summed over the episode so far)."""
        arrived, failed, _ = self.score(task, self.port.observe(task["goal"], task["obstacles"]))
        return arrived or failed or steps >= self.port.horizon, arrived, task["return"]


class CartPoleSim(CartPoleBridge):
    """The cart-pole's topics on the simulator's side: the joint states, the commanded velocity, the outcome."""

    def __init__(self, env: Any, cfg: dict, port: Any):
        super().__init__(port.io, cfg)
        self.env, self.port = env, port

    # ---- the sim's side -------------------------------------------------------------------------------------
    def command_of(self, msg) -> float:
        return float(msg.data) if math.isfinite(msg.data) else 0.0

    def command_of_stamped(self, msg) -> float:
        """The cart command of ``command_stamped``'s JointState (:meth:`CartPoleBridge.stamped_command`): the cart
        joint's velocity."""
        names = list(msg.name)
        cart = self.cfg["joints"]["cart"]
        v = msg.velocity[names.index(cart)] if cart in names and names.index(cart) < len(msg.velocity) else 0.0
        return float(v) if math.isfinite(v) else 0.0

    def zero_command(self):
        return self.start

    def advance(self, command) -> None:
        self.port.advance(command)

    def observed(self, readings: dict) -> None:
        pass  # the cart-pole's outcome and reward read the observation alone

    def task_of(self, task) -> dict:
        return {"command": float(np.asarray(getattr(task, "command", 0.0))), "return": 0.0}

    def task_seen(self, readings: dict, obs: np.ndarray) -> dict:
        return {"return": 0.0}

    def episode_msgs(self, task: dict, t, episode: int) -> dict:
        return {}

    def state_msgs(self, task: dict, t) -> dict:
        from sensor_msgs.msg import JointState

        j = self.port.joints()
        m = JointState()
        m.header.stamp = t
        m.name = [self.cfg["joints"]["cart"], self.cfg["joints"]["pole"]]
        m.position, m.velocity, m.effort = [float(j[0]), float(j[2])], [float(j[1]), float(j[3])], [0.0, 0.0]
        return {"joint_states": m}

    def score(self, task: dict, obs: np.ndarray) -> tuple[bool, bool, float]:
        """``(arrived, failed, reward)`` of the step observed as ``obs``: the cart-pole arrives nowhere, it fails
        with the pole down or the cart out; the task's reward is 1 per step (the episode's return in ``task``)."""
        task["return"] += 1.0
        return False, self.port.terminated(obs), 1.0

    def judge(self, task: dict, steps: int) -> tuple[bool, bool, float]:
        """``(done, success, episode reward)``: the pole down or the cart out ends it, as the horizon does."""
        _, failed, _ = self.score(task, self.port.observe())
        return failed or steps >= self.port.horizon, steps >= self.port.horizon and not failed, task["return"]


def make_bridge(env: Any, topics_path: str | None = None) -> DroneSim | CartPoleSim:
    """The simulator's side of ``env``'s topics (its native port behind them)."""
    fam = family(env)
    cfg = load_topics(fam, topics_path)
    return (DroneSim if fam == "quadcopter" else CartPoleSim)(env, cfg, native_port(env))
