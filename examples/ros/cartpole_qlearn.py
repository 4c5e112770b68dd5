#!/usr/bin/env python
"""The seed's way, against the sim node instead of Gazebo: a rospy task env over the cart-pole's topics, a
``GazeboConnection`` pausing, unpausing and resetting the simulation through the ``/gazebo/*`` services, and the
seed's tabular Q-learning (a dict of state-action values, epsilon-greedy, the first update of a pair sets it to the
reward) on binned observations. Nothing here is jaxrobo's training code: jaxrobo only stands in for Gazebo
(``jaxrobo ros sim``) and supplies the task's parameters (where the seed read its YAML from the parameter server).

    roscore -p 11311 &
    jaxrobo ros sim CartPoleStayUp-v0 --lockstep &
    python examples/ros/cartpole_qlearn.py --episodes 200 --out lengths.json

``--local`` runs the same loop with no ROS at all: the task env drives the sim node's own model, resets and
command handling in this process. Against a ``--lockstep`` sim of the same ``--sim-seed`` it sees the same episodes,
so both give the same episode lengths (what ``tests/test_ros.py`` checks); it is also how to try the learner's
settings quickly.
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import threading
import time

ENV_ID = "CartPoleStayUp-v0"
ACTION_STEPS = (-1.0, 1.0, -10.0, 10.0)  # the seed's cart-pole actions: left, right, left big, right big


class GazeboConnection:
    """The seed's GazeboConnection: pause, unpause and reset through the Gazebo services."""

    def __init__(self, rospy, msgs):
        for name in ("pause_physics", "unpause_physics", "reset_simulation"):
            rospy.wait_for_service(f"/gazebo/{name}", timeout=60)
        self.pause = rospy.ServiceProxy("/gazebo/pause_physics", msgs.Empty, persistent=True)
        self.unpause = rospy.ServiceProxy("/gazebo/unpause_physics", msgs.Empty, persistent=True)
        self.reset = rospy.ServiceProxy("/gazebo/reset_simulation", msgs.Empty, persistent=True)

    def pauseSim(self):
        self.pause()

    def unpauseSim(self):
        self.unpause()

    def resetSim(self):
        self.reset()


class RosCartPole:
    """The robot env over ROS: the velocity command out, the joint states in, the simulation behind Gazebo's
    services. ``reset`` and ``act`` return the joint readings ``(cart x, cart v, pole angle, pole angular v)``."""

    def __init__(self):
        from jaxrobo.ros import msgs
        from jaxrobo_ros.system import rospy as import_rospy

        rospy = import_rospy()
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64

        rospy.init_node("cartpole_qlearn", anonymous=True, disable_signals=True)
        self.rospy, self.Float64 = rospy, Float64
        self.gazebo = GazeboConnection(rospy, msgs)
        self.cmd = rospy.Publisher("/cartpole_v0/foot_joint_velocity_controller/command", Float64, queue_size=1)
        self.cv, self.joints = threading.Condition(), None
        self.sub = rospy.Subscriber("/cartpole_v0/joint_states", JointState, self._on_joints, queue_size=1)
        self._check_publishers_connection()
        # The seed's _check_all_sensors_ready: the simulation's first state, so that a reset's state is told apart
        # from one published before it (stamps grow).
        self.t = self._joints_after(-1.0, timeout=30.0).header.stamp.to_sec()

    def _check_publishers_connection(self, timeout=30.0):
        """The seed's check: a command sent before the simulation's subscriber is connected is lost."""
        end = time.monotonic() + timeout
        while self.cmd.get_num_connections() == 0 or self.sub.get_num_connections() == 0:
            if time.monotonic() > end:
                raise TimeoutError("the simulation's command subscriber or joint-state publisher is not connected")
            time.sleep(0.01)

    def _on_joints(self, msg):
        with self.cv:
            self.joints = msg
            self.cv.notify_all()

    def _joints_after(self, t, timeout=10.0):
        end = time.monotonic() + timeout
        with self.cv:
            while self.joints is None or self.joints.header.stamp.to_sec() <= t:
                if time.monotonic() > end:
                    raise TimeoutError("no /cartpole_v0/joint_states from the simulation")
                self.cv.wait(0.05)
            return self.joints

    def _readings(self, msg):
        self.t = msg.header.stamp.to_sec()
        return msg.position[0], msg.velocity[0], msg.position[1], msg.velocity[1]

    def reset(self):
        self.gazebo.pauseSim()
        self.gazebo.resetSim()
        return self._readings(self._joints_after(self.t))

    def act(self, command):
        self.gazebo.unpauseSim()
        self.cmd.publish(self.Float64(data=command))
        readings = self._readings(self._joints_after(self.t))
        self.gazebo.pauseSim()
        return readings

    def close(self):
        self.rospy.signal_shutdown("done")


class LocalCartPole:
    """The same robot env with no ROS: the sim node's model, resets and command handling in this process (its
    first episode starts with the node; each reset takes the next, as ``/gazebo/reset_simulation`` does)."""

    def __init__(self, sim_seed: int):
        from jaxrobo.ros.bridge import make_bridge, make_env
        from jaxrobo.ros.sim_node import POOL, episode_starts

        env = make_env({"env_id": ENV_ID}, where="ID")
        self.bridge, self.index = make_bridge(env), 0
        self.qpos, self.qvel, _ = episode_starts(env, POOL, sim_seed)

    def _readings(self):
        j = self.bridge.port.joints()
        return float(j[0]), float(j[1]), float(j[2]), float(j[3])

    def reset(self):
        self.index += 1
        i = self.index % len(self.qpos)
        self.bridge.port.reset(self.qpos[i], self.qvel[i])
        return self._readings()

    def act(self, command):
        self.bridge.advance(float(command))
        return self._readings()

    def close(self):
        pass


class CartPoleStayUpEnv:
    """The seed's task env: set_action / get_obs / is_done / compute_reward over a robot env."""

    def __init__(self, robot):
        import jaxrobo

        self.p = jaxrobo.make(ENV_ID).default_params  # the seed: rospy.get_param(...)
        self.robot = robot

    def reset(self):
        self.pos = 0.0  # the seed's accumulated velocity command
        return self.robot.reset()

    def step(self, action):
        vmax = float(self.p.max_base_velocity)
        self.pos = min(max(self.pos + ACTION_STEPS[action] * float(self.p.pos_step), -vmax), vmax)
        obs = self.robot.act(self.pos)
        p = self.p
        done = not (float(p.min_base_pose_x) < obs[0] < float(p.max_base_pose_x)
                    and float(p.min_pole_angle) < obs[2] < float(p.max_pole_angle))
        return obs, 1.0, done


def state(obs):
    """Bins of cart velocity, pole angle and pole angular velocity (jaxrobo's CartPoleStayUp preset: the cart's
    position is left out, its velocity keeps it near the middle)."""
    bins = ((-1.0, 1.0, 6), (-0.3, 0.3, 8), (-2.0, 2.0, 10))
    return tuple(min(max(int((x - lo) / (hi - lo) * n), 0), n - 1) for x, (lo, hi, n) in zip(obs[1:], bins))


class QLearn:
    """The seed's qlearn.py."""

    def __init__(self, actions, epsilon, alpha, gamma):
        self.q, self.actions, self.epsilon, self.alpha, self.gamma = {}, actions, epsilon, alpha, gamma

    def chooseAction(self, state):
        if random.random() < self.epsilon:
            return random.choice(self.actions)
        q = [self.q.get((state, a), 0.0) for a in self.actions]
        best = max(q)
        return random.choice([a for a, v in zip(self.actions, q) if v == best])

    def learn(self, s, a, r, s2, done):
        best = 0.0 if done else max(self.q.get((s2, b), 0.0) for b in self.actions)  # nothing follows a fall
        old = self.q.get((s, a))
        self.q[(s, a)] = r if old is None else old + self.alpha * (r + self.gamma * best - old)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--nsteps", type=int, default=200)
    ap.add_argument("--alpha", type=float, default=0.5)
    ap.add_argument("--gamma", type=float, default=0.99)
    ap.add_argument("--epsilon", type=float, default=0.3)
    ap.add_argument("--epsilon-discount", type=float, default=0.97)
    ap.add_argument("--seed", type=int, default=0, help="the learner's random seed")
    ap.add_argument("--local", action="store_true", help="no ROS: the sim node's model in this process")
    ap.add_argument("--sim-seed", type=int, default=0, help="with --local: the sim's --seed (its resets)")
    ap.add_argument("--out", default=None, help="write the episode lengths here (JSON)")
    args = ap.parse_args(argv)
    for name in ("episodes", "nsteps"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    random.seed(args.seed)
    env = CartPoleStayUpEnv(LocalCartPole(args.sim_seed) if args.local else RosCartPole())
    agent = QLearn(list(range(len(ACTION_STEPS))), args.epsilon, args.alpha, args.gamma)
    lengths, t0 = [], time.monotonic()
    for episode in range(args.episodes):
        agent.epsilon = max(agent.epsilon * args.epsilon_discount, 0.01)
        s = state(env.reset())
        for step in range(args.nsteps):
            a = agent.chooseAction(s)
            obs, r, done = env.step(a)
            s2 = state(obs)
            agent.learn(s, a, r, s2, done)
            s = s2
            if done:
                break
        lengths.append(step + 1)
        if (episode + 1) % 25 == 0:
            print(f"episodes {episode - 23}-{episode + 1}: mean length {sum(lengths[-25:]) / 25:.1f} "
                  f"(epsilon {agent.epsilon:.3f}, {time.monotonic() - t0:.0f} s)", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(lengths, f)
    env.robot.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
