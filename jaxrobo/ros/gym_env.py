"""A Gymnasium env over live ROS topics, the seed's structure literally: ``step`` = unpause physics, publish the
command of the action (the task's mapping), wait one control period of stamp time for the state, pause physics,
then observation (the task's native port on the readings, as training built it), termination and reward; ``reset``
= ``/gazebo/reset_simulation`` and the first state (from a sim that numbers its episodes on ``/jaxrobo/episode``:
with the next number, and the drone's goal and obstacles of that episode). It evaluates a jaxrobo policy, or any
Gymnasium agent, on whatever answers on the topics: ``jaxrobo ros sim ID`` (without ``--episodes``), Gazebo, a
robot.

    import gymnasium as gym, jaxrobo.ros
    env = gym.make("jaxrobo-ros/QuadcopterGoto-v2")   # a master and a sim must be up (docs/ros.md)

Reward: the task's own, computed from the readings by the code that sums it for the sim's ``/openai/reward``
(:meth:`jaxrobo.ros.bridge.DroneSim.score`): the cart-pole's 1 per step, the drone's shaped reward (progress, step
and altitude costs, arrival bonus, crash penalty, v2's heading and climb shaping) with ``info["arrived"]`` and
``info["crashed"]``; the potentials start from the reset's first observation. Truncation at the task's
``max_episode_steps``.
"""
from __future__ import annotations

import threading
import time
from typing import Any

import gymnasium
import numpy as np

from jaxrobo_ros.system import rospy as import_rospy
from jaxrobo.ros.bridge import make_bridge, make_env, ros_ids
from jaxrobo_ros.bridge import Fault, stamp



class RosTaskEnv(gymnasium.Env):
    metadata = {"render_modes": []}

    def __init__(self, env_id: str, topics: str | None = None, timeout: float = 10.0, params: dict | None = None):
        """``params``: the task's options and parameters that differ from its defaults (as ``jaxrobo.make``
        takes them; a dict, since Gymnasium's ``make`` keeps ``max_episode_steps`` for itself)."""
        self.rospy = rospy = import_rospy()
        from jaxrobo.ros import msgs

        self.task_env = make_env({"env_id": env_id, "env_params": dict(params or {})}, where="params")
        self.b = make_bridge(self.task_env, topics)
        self.timeout = timeout
        n = self.task_env.observation_space().shape[0]
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (n,), np.float32)
        a = self.task_env.action_space()
        self.action_space = (gymnasium.spaces.Box(np.asarray(a.low, np.float32), np.asarray(a.high, np.float32))
                             if hasattr(a, "low") else gymnasium.spaces.Discrete(int(a.n)))
        if not rospy.core.is_initialized():
            rospy.init_node("jaxrobo_gym", anonymous=True, disable_signals=True)
        types, top = self.b.msg_types(), self.b.topics
        self.latest: dict[str, Any] = {}
        self.cv = threading.Condition()
        self.subs = [rospy.Subscriber(top[k], types[k], self._on_msg, callback_args=k, queue_size=1,
                                      tcp_nodelay=True) for k in self.b.sensors]
        self.pub = rospy.Publisher(top[self.b.command_topic], types[self.b.command_topic], queue_size=1,
                                   tcp_nodelay=True)
        self.srv = {name: rospy.ServiceProxy(f"/gazebo/{name}", msgs.Empty, persistent=True)
                    for name in ("pause_physics", "unpause_physics", "reset_simulation")}
        self.horizon = int(self.task_env.default_params.max_episode_steps)
        end = time.monotonic() + timeout
        while self.pub.get_num_connections() == 0:  # a command sent before that would be lost
            if time.monotonic() > end:
                raise TimeoutError(f"nothing subscribes to {top[self.b.command_topic]} after {timeout:g} s")
            time.sleep(0.01)
        self.t, self.steps, self.episode = -np.inf, 0, None

    def _on_msg(self, msg, name: str) -> None:
        with self.cv:
            self.latest[name] = msg
            self.cv.notify_all()

    def _call(self, name: str) -> None:
        self.rospy.wait_for_service(f"/gazebo/{name}", timeout=self.timeout)
        self.srv[name]()

    def _state_after(self, t: float, episode: int | None = None) -> tuple[np.ndarray, dict]:
        """The observation of the first complete set of readings stamped after ``t`` (the drone's: with the goal and
        obstacles of the episode they are in, :meth:`jaxrobo_ros.bridge.DroneBridge.current`), in another episode
        than ``episode`` where one is given."""
        end = time.monotonic() + self.timeout
        why = "no reading"
        with self.cv:
            while time.monotonic() < end:
                if episode is not None and self.b.episode_of(self.latest) in (None, episode):
                    why = f"no {self.b.topics['episode']} after episode {episode}"
                elif self.b.primary in self.latest and stamp(self.latest[self.b.primary]) > t:
                    try:
                        latest = dict(self.latest)
                        return self.b.observation(latest), latest
                    except Fault as err:
                        if not err.waiting:
                            raise
                        why = str(err)
                self.cv.wait(0.01)
        raise TimeoutError(f"no state after {t:.3f} s within {self.timeout:g} s ({why})")

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._call("pause_physics")
        # The readings the topics hold before the reset: the reset's first state is the first stamped after them
        # (a reading of the state before the reset, still in flight, is not taken for it).
        _, before = self._state_after(-np.inf)
        t0 = max(self.t, stamp(before[self.b.primary]))
        # A sim that numbers its episodes (jaxrobo ros sim): the reset's first state is taken with the next
        # episode's number and, for the drone, that episode's goal and obstacles (each travels over a connection
        # of its own, and may arrive after the state).
        episode = self.b.episode_of(before)
        self._call("reset_simulation")
        self.b.reset_memory()
        obs, latest = self._state_after(t0, episode)
        self.t, self.steps = stamp(latest[self.b.primary]), 0
        self.episode = self.b.task_seen(self.b.readings(latest), obs)
        return obs, {}

    def step(self, action):
        self._call("unpause_physics")
        self.pub.publish(self.b.command_msg(action))
        obs, latest = self._state_after(self.t + 0.5 * self.b.period)
        self._call("pause_physics")
        self.t = stamp(latest[self.b.primary])
        self.steps += 1
        self.b.observed(self.b.readings(latest))
        arrived, failed, reward = self.b.score(self.episode, obs)
        info = {"arrived": arrived, "crashed": failed} if self.b.family == "quadcopter" else {}
        terminated = arrived or failed
        return obs, reward, terminated, self.steps >= self.horizon and not terminated, info

    def close(self) -> None:
        for s in getattr(self, "subs", []):
            s.unregister()
        for p in getattr(self, "srv", {}).values():
            p.close()


def register() -> None:
    for env_id in ros_ids():
        gid = f"jaxrobo-ros/{env_id}"
        if gid not in gymnasium.registry:
            gymnasium.register(id=gid, entry_point=f"{__name__}:RosTaskEnv", kwargs={"env_id": env_id})
