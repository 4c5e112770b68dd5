"""``jaxrobo ros sim ID``: the Gazebo stand-in. The task's robot in native MuJoCo (its own compiled model, on-board
controllers and control period: the port in ``envs/*/native.py``) behind the seed's topics and services.

Each control period (while not paused) it holds the last command for ``n_substeps`` ``mj_step`` calls, then
publishes ``/clock`` and the state topics stamped with sim time. ``--lockstep`` waits for one command per published
state before the next period (deterministic: a policy answering each state sees exactly the native loop's
episodes; Gazebo has no such mode), otherwise it runs at ``--speed`` x real time holding the last command.

In lockstep each state is stepped once, with one command: the first that answers it. The command topics carry no
stamp, so a node sends, beside each command, a copy stamped with the state it answers on ``command_stamped`` (the
policy node does): the sim steps on the copy stamped with the state it waits on, drops a copy that answers a state
already stepped (a late answer, or the policy node's copy of it sent again when the state was republished) or a
second answer, and does not take the plain commands of a node that sends stamped copies. From a node that sends
none (the Gymnasium env over ROS, a seed-style script) the first plain command received after a state went out
answers it: such a client must send one command per state. A state republished after ``REPUBLISH`` s keeps its
stamp and its answer. A stamped copy that names another episode than the state's (``header.frame_id``,
:func:`jaxrobo_ros.bridge.episode_tag`: the policy node answered a new episode's first state before its number, sent
over another connection, reached it, so with the last episode's accumulated cart command) is dropped too: the state is
republished and answered afresh. ``/jaxrobo/episode`` carries each episode's number and start stamp (a
``std_msgs/Header``, :func:`jaxrobo_ros.bridge.episode_msg`); the drone's goal (frame ``world``) is stamped with that
start and the obstacle array names its episode (``layout.dim[0].label``), and the policy node and the Gymnasium env
over ROS wait for those of the episode they are in. ``EPISODE_MARGIN`` only makes these waits and drops rare (a
speed measure); the stamps and tags, not the margin, keep lockstep exact.

Episodes start from the task's own resets (``jaxrobo.task.rollout.rollout_start`` with key ``--seed``: episode ``i``
is the ``i``-th reset of ``jaxrobo eval``/``scripts/sim2sim.py`` with that key). With ``--episodes N`` the sim runs
``N`` episodes back to back (a new one when the task ends one or at the horizon), publishes each one's return on
``/openai/reward`` (the task's own reward summed over the episode, as openai_ros does: the cart-pole's 1 per step,
the drone's shaped reward of ``envs/quadcopter/goto*.py``), writes ``--results`` and exits; without it episodes
change only on ``/gazebo/reset_simulation`` or ``/gazebo/reset_world`` (as a seed training script drives Gazebo).
``/gazebo/pause_physics`` and ``/gazebo/unpause_physics`` stop and resume time.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from typing import Any

import numpy as np

from jaxrobo_ros.bridge import episode_msg, tagged_episode
from jaxrobo_ros.system import line_buffered, rospy as import_rospy, stop_on_signals
from jaxrobo.core.config import ConfigError, parse_json
from jaxrobo.ros.bridge import make_bridge, make_env

#: Wall-clock seconds between a new episode's goal, obstacles and number (latched topics) and its first state: a
#: speed measure only. Topics travel over separate connections, so a subscriber usually has them before the state
#: and need not wait for them, or answer the state again; the episode stamps and tags make it right when it does not.
EPISODE_MARGIN = 0.05
#: Wall-clock seconds without a step (paused, or waiting for a lockstep command) before the sim publishes its
#: state again (same stamp).
REPUBLISH = 0.5
#: Without ``--episodes``: the resets drawn ahead; episode ``i`` starts from reset ``i % POOL``.
POOL = 1000


def episode_starts(env: Any, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, list]:
    """The first ``n`` resets of key ``seed`` as :func:`jaxrobo.task.rollout.rollout` draws them: qpos, qvel and
    each episode's task variables (host arrays)."""
    import jax

    from jaxrobo.task.rollout import rollout_start

    first = jax.jit(lambda k: rollout_start(env, k, n)["first"])(jax.random.key(seed))
    qpos = np.asarray(jax.vmap(env.robot.sim.qpos)(first.pipeline_state), np.float64)
    qvel = np.asarray(jax.vmap(env.robot.sim.qvel)(first.pipeline_state), np.float64)
    task = jax.tree.map(np.asarray, first.task)
    return qpos, qvel, [jax.tree.map(lambda x: x[i], task) for i in range(n)]


class SimNode:
    def __init__(self, env: Any, episodes: int, seed: int, lockstep: bool, speed: float, topics: str | None = None,
                 pool: int = POOL, ros_args=()):
        """``ros_args``: the node's own ``name:=value`` arguments (remappings, ``__name``, ...) for rospy."""
        self.rospy = rospy = import_rospy()
        from rosgraph_msgs.msg import Clock

        from jaxrobo.ros import msgs

        self.b = make_bridge(env, topics)
        self.episodes, self.lockstep, self.speed = episodes, lockstep, speed
        self.qpos, self.qvel, self.tasks = episode_starts(env, episodes or pool, seed)
        self.lock = threading.Condition()
        self.paused = False
        # lockstep: the stamp of the state waiting for its command, the command answering it (None: not yet), the
        # commands dropped as answers to a state already stepped or as second answers
        self.out, self.answer, self.dropped = None, None, 0
        self.t, self.steps, self.index, self.results = 0.0, 0, -1, []
        self.tick = self.published = time.monotonic()  # wall clock: the period's end, the last publication
        self.command = self.b.zero_command()
        self.msgs = msgs
        rospy.init_node("jaxrobo_sim", argv=[sys.argv[0], *ros_args], disable_signals=True)
        types = self.b.msg_types()
        top = self.b.topics
        latched = {"goal", "obstacles", "episode"}
        self.pubs = {k: rospy.Publisher(top[k], types[k], queue_size=10, latch=k in latched)
                     for k in types if k not in (self.b.command_topic, "takeoff", "land")}
        self.clock = rospy.Publisher("/clock", Clock, queue_size=10)
        self.reward = rospy.Publisher("/openai/reward", msgs.RLExperimentInfo, queue_size=10)
        self.Clock, self.Info = Clock, msgs.RLExperimentInfo
        # lockstep: the commands' stamped copies (subscribed first: a node found on the command topic is on this one)
        self.stamped = rospy.Subscriber(top["command_stamped"], self.b.stamped_type(), self._on_stamped,
                                        queue_size=10, tcp_nodelay=True) if lockstep else None
        rospy.Subscriber(top[self.b.command_topic], types[self.b.command_topic], self._on_command, queue_size=10,
                         tcp_nodelay=True)
        for name, fn in (("pause_physics", self._pause), ("unpause_physics", self._unpause),
                         ("reset_simulation", self._reset), ("reset_world", self._reset)):
            rospy.Service(f"/gazebo/{name}", msgs.Empty, fn)

    # ---- callbacks (rospy's threads) ------------------------------------------------------------------------
    def _on_command(self, msg) -> None:
        with self.lock:
            if not self.lockstep:
                self.command = self.b.command_of(msg)  # held from the next period on
            elif not self._stamps(msg):  # a node that sends stamped copies answers with those alone
                self._answer(self.b.command_of(msg))

    def _on_stamped(self, msg) -> None:
        with self.lock:
            if msg.header.stamp == self.out and tagged_episode(msg) in (None, self.index):
                self._answer(self.b.command_of_stamped(msg))
            else:
                # it answers a state already stepped (late, or sent again), or none published, or was computed in
                # another episode than this state's (the node had not yet heard of it: the episode number and the
                # states travel over separate connections); the state is republished after REPUBLISH s
                self.dropped += 1

    def _stamps(self, msg) -> bool:
        """Whether the node that published ``msg`` also publishes stamped copies to this node (is connected to it on
        ``command_stamped``)."""
        caller = (getattr(msg, "_connection_header", None) or {}).get("callerid")
        return caller is not None and any((getattr(c, "header", None) or {}).get("callerid") == caller
                                          for c in list(self.stamped.impl.connections or ()))

    def _answer(self, command) -> None:
        """``command`` answers the state out, unless another did already: the state is stepped once."""
        if self.out is None or self.answer is not None:
            self.dropped += 1
            return
        self.answer = command
        self.lock.notify_all()

    def _pause(self, _req):
        with self.lock:
            self.paused = True
        return self.msgs.EmptyResponse()

    def _unpause(self, _req):
        with self.lock:
            self.paused = False
            self.tick = time.monotonic()  # time resumes now: a whole period before the next step
            self.lock.notify_all()
        return self.msgs.EmptyResponse()

    def _reset(self, _req):
        with self.lock:
            self.new_episode()
        return self.msgs.EmptyResponse()

    # ---- the simulation ---------------------------------------------------------------------------------------
    def stamp(self):
        return self.rospy.Time.from_sec(self.t)

    def new_episode(self) -> None:
        """The next reset: its state, goal and episode number published (the goal first), time one period on."""
        self.index += 1
        i = self.index % len(self.tasks)
        self.task = self.b.task_of(self.tasks[i])
        self.b.port.reset(self.qpos[i], self.qvel[i])
        self.command = self.task.get("command", self.b.zero_command())
        self.steps, self.t = 0, self.t + self.b.period
        start = self.stamp()  # the first state's, the goal's and the episode message's: a goal's stamp says its episode
        for k, m in self.b.episode_msgs(self.task, start, self.index).items():
            self.pubs[k].publish(m)
        self.pubs["episode"].publish(episode_msg(self.index, start))
        time.sleep(EPISODE_MARGIN)
        self.publish_state()
        self.tick = time.monotonic()  # the first period of the episode is a whole one

    def publish_state(self, again: bool = False) -> None:
        """The state now; ``again``: the same state once more (same stamp; an answer it had stays its answer)."""
        self.published = time.monotonic()
        if not again:  # a new state: nothing answers it yet (lockstep)
            self.out, self.answer = self.stamp(), None
        self.clock.publish(self.Clock(clock=self.stamp()))
        for k, m in self.b.state_msgs(self.task, self.stamp()).items():
            self.pubs[k].publish(m)

    def step(self) -> None:
        if self.lockstep:
            self.command, self.answer, self.out = self.answer, None, None  # taken: no other command answers it
        self.b.advance(self.command)
        self.steps += 1
        self.t += self.b.period
        done, success, reward = self.b.judge(self.task, self.steps)
        if done and self.episodes:
            self.results.append({"episode": self.index, "steps": self.steps, "success": bool(success),
                                 "reward": reward})
            self.reward.publish(self.Info(episode_number=self.index, episode_reward=reward))
            if len(self.results) >= self.episodes:
                return  # as after every episode, its end state is not published (the policy has no step left)
            self.new_episode()
        else:
            self.publish_state()

    def ready(self) -> bool:
        return not self.paused and (not self.lockstep or self.answer is not None)

    def run(self, stopping: list) -> list[dict]:
        """Episodes until ``stopping`` (:func:`jaxrobo_ros.system.stop_on_signals`) is not empty."""
        with self.lock:
            self.new_episode()
        while not stopping and not self.rospy.is_shutdown():
            with self.lock:
                if not self.ready():
                    self.lock.wait(0.05)
                    if not self.ready() and time.monotonic() - self.published > REPUBLISH:
                        self.publish_state(again=True)  # for a subscriber that connected after it, or lost its answer
                    continue
                if self.speed > 0 and not self.lockstep:
                    self.tick += self.b.period / self.speed
                    if self.tick < time.monotonic():
                        self.tick = time.monotonic()  # behind: no catching up in a burst
                    while time.monotonic() < self.tick:  # commands arrive meanwhile; the period ends with the last
                        self.lock.wait(self.tick - time.monotonic())
                self.step()
                if self.episodes and len(self.results) >= self.episodes:
                    break
        return self.results


def run(args) -> int:
    line_buffered()  # its log lines reach a log file as they are written

    if os.path.isdir(args.env_id):  # an export: its task with the run's options and parameters
        from jaxrobo.interop.numpy_policy import POLICY_JSON

        try:
            with open(os.path.join(args.env_id, POLICY_JSON)) as f:
                meta = parse_json(f.read())
        except (OSError, ValueError) as err:
            raise ConfigError(f"{args.env_id}: not an export ({err})") from None
        env = make_env(meta if isinstance(meta, dict) else {}, where=os.path.join(args.env_id, POLICY_JSON))
        args.env_id = env.spec.id
    else:
        env = make_env({"env_id": args.env_id}, where="ID")
    node = SimNode(env, args.episodes, args.seed, args.lockstep, args.speed, args.topics, ros_args=args.ros_args)
    stopping = stop_on_signals()
    print(f"jaxrobo ros sim: {args.env_id} in native MuJoCo as {node.rospy.get_name()}, control period "
          f"{node.b.period:g} s, "
          f"{'lockstep' if args.lockstep else f'{args.speed:g} x real time'}", flush=True)
    results = node.run(stopping)
    if args.results:
        with open(args.results, "w") as f:
            json.dump({"env_id": args.env_id, "seed": args.seed, "episodes": results}, f)
    if results:
        rate = np.mean([r["success"] for r in results])
        print(f"jaxrobo ros sim: {len(results)} episodes, success {rate:.3f}, mean steps "
              f"{np.mean([r['steps'] for r in results]):.1f}", flush=True)
    if node.dropped:
        print(f"jaxrobo ros sim: dropped {node.dropped} late or repeated answer{'s' * (node.dropped != 1)} "
              "(lockstep: each state is stepped once)", flush=True)
    node.rospy.signal_shutdown("done")
    return 0
