"""``python -m jaxrobo_ros.policy_node EXPORT_DIR`` (or ``jaxrobo ros policy EXPORT_DIR``): an exported policy as a
rospy node on the task's topics (``topics/<family>.yaml``), from the export alone: the export's own numpy runner
(``jaxrobo_policy.py``, loaded from the directory) and its ``robot`` section (the task's control period,
observation constants and action table). numpy, yaml and rospy only: JAX is not imported.

It acts once per control period of sim or sensor time: when the primary reading (odometry, joint states) of a new
period has arrived together with every other reading it needs within ``max_age`` of it, it builds the task's
observation with the export's ``robot`` section (:mod:`jaxrobo_ros.bridge`: the training's numbers, units and
frames, computed by the same code as the task's native port), runs the policy and publishes the command, from the
callback of the message that completed the set (no queue between message in and command out), and the same command
stamped with the state it answers on ``command_stamped`` (what a lockstep sim steps on: docs/ros.md). The same state
again (a lockstep sim republishes a state it has no command for) is answered with the same command again, both
copies. A missing, stale or non-finite reading, or none at all for ``stale_after``
wall-clock seconds (a sim or sensor that died), stops the robot: a zero command and one warning saying why, repeated
while the cause lasts; the node keeps running and acts again once fresh readings arrive. A reading stamped before
the last one (Gazebo's ``reset_simulation`` rewinds time) or a new ``/jaxrobo/episode`` starts a new episode (the
cart-pole's accumulated command returns to its start value). The stamped copy names the episode it was computed in
(``header.frame_id``, :func:`jaxrobo_ros.bridge.episode_tag`): a lockstep sim does not step on an answer to a new
episode's first state computed before the node heard of that episode, and republishes the state. The drone's goal
and obstacles count only in their own episode (:meth:`jaxrobo_ros.bridge.Bridge.episode_check`: the goal's stamp is
its episode's start, which ``/jaxrobo/episode`` carries, the obstacles name theirs): a new episode's state waits for
its own goal and obstacles, and is acted on from the callback of the one that completes the set; a state that
arrived before its episode's number (stamped from the episode's start on), from the number's.

An export without a ``robot`` section (written before exports carried one, or of a task without a native port)
is refused with one line saying to export it again.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from jaxrobo_ros.bridge import Fault, episode_tag, make_bridge, stamp
from jaxrobo_ros.system import SetupError, line_buffered, rospy as import_rospy, stop_on_signals

#: The numpy runner ``jaxrobo export`` copies into every export.
RUNNER = "jaxrobo_policy.py"

#: Exit status after the master was restarted under the node (a supervisor's cue to start it again).
EXIT_MASTER_LOST = 3
#: Commands whose latency and timing the node keeps for ``--stats`` (the most recent ones).
HISTORY = 100_000


class PolicyNode:
    def __init__(self, export_dir: str, topics: str | None = None, ros_args=()):
        """``ros_args``: the node's own ``name:=value`` arguments (remappings, ``__name``, ...) for rospy."""
        self.ros_args = list(ros_args)
        self.policy = load_export(export_dir)
        self.b = make_bridge(self.policy.io, topics)
        self.rospy = import_rospy()
        self.latest: dict[str, Any] = {}
        self.lock = threading.Lock()
        self.next_due, self.last_t = -np.inf, -np.inf
        self.last_act = time.monotonic()
        self.commands = 0
        self.goal = None  # the goal parameter's value, where the topic file names one (else the goal topic)
        self.master_lost: str | None = None
        self.closing = False  # set by stop(): a reading that arrives later sends nothing (its topic is closing)
        self.fault: str | None = None
        self.last_out, self.acted_t = None, None  # the last command sent, and the stamp it answered
        self.last_stamped = None  # the last command again, stamped with the state it answered
        self.latency: deque = deque(maxlen=HISTORY)  # s, message in -> command out
        self.acted: deque = deque(maxlen=HISTORY)  # (wall s, stamp s) of each command

    def start(self) -> None:
        rospy = self.rospy
        rospy.init_node("jaxrobo_policy", argv=[sys.argv[0], *self.ros_args], disable_signals=True)
        types, top = self.b.msg_types(), self.b.topics
        self.stamped_pub = rospy.Publisher(top["command_stamped"], self.b.stamped_type(), queue_size=1,
                                           tcp_nodelay=True)
        self.pub = rospy.Publisher(top[self.b.command_topic], types[self.b.command_topic], queue_size=1,
                                   tcp_nodelay=True)
        if self.b.family == "quadcopter" and self.b.cfg.get("goal_param"):
            self.goal = self._goal_param()  # before any reading can arrive
        for name in self.b.sensors:
            rospy.Subscriber(top[name], types[name], self._on_msg, callback_args=name, queue_size=1,
                             tcp_nodelay=True)
        if "takeoff" in top:
            rospy.Publisher(top["takeoff"], types["takeoff"], queue_size=1, latch=True).publish(types["takeoff"]())
        threading.Thread(target=self._watch_master, daemon=True).start()

    def _watch_master(self) -> None:
        """Every second, the master's pid: one that no longer answers is reported (the connections already made
        keep working); one that answers with another pid was restarted, and rospy does not register this node with
        it again, so the node stops the robot and ends (``master_lost``) for a supervisor to start it again."""
        import rosgraph

        master, pid, silent = rosgraph.Master(self.rospy.get_name()), None, False
        while not self.rospy.is_shutdown():
            try:
                now = master.getPid()
            except Exception as err:  # noqa: BLE001 - any failure to reach it is "does not answer"
                if not silent:
                    self.rospy.logwarn(f"jaxrobo ros policy: the ROS master at {master.master_uri} does not answer "
                                       f"({type(err).__name__}); connections already made keep working")
                silent = True
            else:
                if pid is not None and now != pid:
                    self.master_lost = (f"the ROS master at {master.master_uri} was restarted (pid {pid} -> {now}) "
                                        "and does not know this node: start it again")
                    return
                pid, silent = now, False
            time.sleep(1.0)

    def _goal_param(self):
        name = self.b.cfg["goal_param"]
        g = self.rospy.get_param(name, None)
        try:
            g = np.asarray(g, np.float64).reshape(3)
            assert np.all(np.isfinite(g))
        except (TypeError, ValueError, AssertionError):
            raise SetupError(f"parameter {name}: expected [x, y, z] (m), got {g!r}") from None
        return g

    # ---- acting (rospy's callback threads) -------------------------------------------------------------------
    def _on_msg(self, msg, name: str) -> None:
        t_in = time.perf_counter()
        with self.lock:
            if self.closing:  # stop() sent the zero command: nothing after it (rospy closes the topics next)
                return
            # the episode lives in latest["episode"] alone: the one before this message's, to tell a new one
            previous = self.b.episode_of(self.latest) if name == "episode" else None
            self.latest[name] = msg
            if name == "episode":
                if previous is not None and int(msg.seq) != previous:
                    self._new_episode(msg.stamp.to_sec())  # the number carries its episode's start
                if self.b.primary not in self.latest:
                    return
                # a state held for its episode's number (stamped from the episode's start on) is acted on now
                t = stamp(self.latest[self.b.primary])
            elif name != self.b.primary and self.b.primary in self.latest:
                # a reading that completes the set: a sonar, or the goal and obstacles a held state waits for
                t = stamp(self.latest[self.b.primary])
            elif name == self.b.primary:
                t = stamp(msg)
                if self.last_t == -np.inf:
                    self.last_act = time.monotonic()  # the watchdog counts from the first reading
                if t < self.last_t:  # time rewound: a reset of the simulation
                    self._new_episode()
                    self.latest[name] = msg  # the first reading of the new episode
                elif t == self.acted_t and self.last_out is not None and self.fault is None:
                    # the same state again: its command was lost or is late; send it again (a late one then
                    # reaches a lockstep sim twice, and the sim steps on the first stamped copy only)
                    self.pub.publish(self.last_out)
                    self.stamped_pub.publish(self.last_stamped)
                    return
                self.last_t = t
            else:
                return
            if t < self.next_due - 1e-6:  # acted on already (a goal or sonar after the command)
                return
            try:
                obs = self.b.observation(self.latest, self.goal)
                if not np.all(np.isfinite(obs)):
                    raise Fault(f"observation {obs.tolist()} is not finite")
            except Fault as err:
                # a reading not there yet may be on its way (one moment's readings travel over several
                # connections): the watchdog stops the robot if it does not come; a bad value stops it now
                if not err.waiting:
                    self._hold(str(err))
                return
            out = self.b.command_msg(self.policy(obs))
            self.pub.publish(out)
            stamped = self.b.stamped_command(out, self.latest[self.b.primary].header.stamp)
            episode = self.b.episode_of(self.latest)
            if episode is not None:
                # the episode whose start this answer counts from: a new episode's first state can arrive before
                # its number (another connection); a lockstep sim does not step on an answer of another episode
                stamped.header.frame_id = episode_tag(episode)
            self.stamped_pub.publish(stamped)
            self.last_out, self.last_stamped, self.acted_t = out, stamped, t
            self.latency.append(time.perf_counter() - t_in)
            self.commands += 1
            now = time.monotonic()
            self.acted.append((now, t))
            self.last_act, self.next_due = now, t + self.b.period
            if self.fault is not None:
                self.rospy.loginfo("jaxrobo ros policy: acting" + ("" if self.fault == "waiting" else
                                                                   f" again ({self.fault} has cleared)"))
                self.fault = None

    def _new_episode(self, start: float | None = None) -> None:
        """Forget the last episode: its readings (those stamped from ``start``, the new episode's start, on are this
        one's: a first state that arrived before the episode's number), its command memory."""
        self.b.reset_memory()
        self.last_out = None
        self.next_due = -np.inf
        for k in list(self.latest):  # readings of the last episode say nothing of this one
            if k not in ("goal", "obstacles", "episode") and (start is None or stamp(self.latest[k]) < start):
                del self.latest[k]

    def _hold(self, why: str) -> None:
        """Stop the robot (zero command) and say why, once per new cause."""
        self.pub.publish(self.b.zero_msg())
        self.last_act = time.monotonic()
        if why != self.fault:
            self.rospy.logwarn(f"jaxrobo ros policy: stopping the robot (zero command): {why}")
            self.fault = why

    def watch(self) -> None:
        """Called every few ms from the main thread: no command for ``stale_after`` s stops the robot."""
        with self.lock:
            idle = time.monotonic() - self.last_act
            if idle < self.b.stale_after:
                return
            if self.b.primary not in self.latest and self.last_t == -np.inf:
                # nothing heard yet: nothing was commanded, so nothing to stop (and a lockstep sim would take a
                # command sent now for the answer to its first state)
                if self.fault is None:
                    self.rospy.logwarn(f"jaxrobo ros policy: waiting for {self.b.topics[self.b.primary]}")
                    self.fault = "waiting"
                return
            try:
                self.b.observation(self.latest, self.goal)
                why = f"no new {self.b.topics[self.b.primary]} for {idle:.1f} s"
            except Fault as err:
                why = f"{err} (nothing acted on for {idle:.1f} s)"
            self._hold(why)

    def stats(self) -> dict:
        lat = np.asarray(self.latency) * 1e3
        wall = np.diff([a[0] for a in self.acted]) if len(self.acted) > 1 else np.zeros(0)
        q = lambda a, p: float(np.percentile(a, p)) if a.size else None  # noqa: E731
        return {"commands": self.commands, "latency_ms": {"median": q(lat, 50), "p99": q(lat, 99),
                                                              "max": q(lat, 100)},
                "loop_period_s": {"median": q(wall, 50), "p99": q(wall, 99)},
                "loop_rate_hz": (1.0 / q(wall, 50)) if wall.size and q(wall, 50) > 0 else None}

    def stop(self) -> None:
        with self.lock:  # after a reading's command in flight, before any later one
            self.closing = True
            self.pub.publish(self.b.zero_msg())
        top, types = self.b.topics, self.b.msg_types()
        if "land" in top:
            self.rospy.Publisher(top["land"], types["land"], queue_size=1, latch=True).publish(types["land"]())
        time.sleep(0.1)  # let the last messages leave


def load_export(export_dir: str) -> Any:
    """The policy of ``export_dir`` by the export's own runner, with its ``robot`` side (``policy.io``);
    :class:`SetupError` in one line where the directory is not such an export."""
    path = os.path.join(export_dir, RUNNER)
    again = f"export it again (jaxrobo export RUN --out {export_dir} --overwrite)"
    if not os.path.isfile(path):
        raise SetupError(f"{export_dir}: no {RUNNER}: not a directory written by jaxrobo export")
    try:
        spec = importlib.util.spec_from_file_location(f"jaxrobo_policy_{abs(hash(os.path.abspath(path)))}", path)
        runner = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(runner)
        policy = runner.Policy.load(export_dir)
    except ValueError as err:
        raise SetupError(str(err)) from None
    except Exception as err:  # noqa: BLE001 - a runner that does not even load: one line, naming it
        raise SetupError(f"{path}: cannot be loaded ({type(err).__name__}: {err}); {again}") from None
    if getattr(policy, "io", None) is None:
        env_id = policy.meta.get("env_id")
        raise SetupError(f"{export_dir}: policy.json has no robot section (the task's observation constants, "
                         f"control period and action table) for {env_id}: exported before exports carried one, "
                         f"or a task without a native port; {again}")
    if policy.io.observation_size != policy.obs_size:
        raise SetupError(f"{export_dir}: the policy takes {policy.obs_size} observations, its robot section "
                         f"({policy.io.family}) gives {policy.io.observation_size}")
    return policy


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("export_dir", metavar="EXPORT_DIR", help="a directory written by `jaxrobo export`")
    p.add_argument("--topics", default=None, help="topic YAML (default: jaxrobo_ros/topics/<family>.yaml)")
    p.add_argument("--stats", default=None, help="write the latency and loop-rate figures here (JSON) at exit")
    # ROS's own name:=value arguments (topic remappings, __name, as roslaunch and rosrun give them) are taken out
    # of the command line before it is parsed (jaxrobo_ros.system.split_ros_args) and handed to rospy
    p.set_defaults(ros_args=[])


def main(argv=None) -> int:
    """``python -m jaxrobo_ros.policy_node``: the node without the jaxrobo command line (and without JAX)."""
    from jaxrobo_ros.system import split_ros_args, unavailable_reason

    p = argparse.ArgumentParser(prog="python -m jaxrobo_ros.policy_node", description=__doc__.split("\n\n")[0])
    configure_parser(p)
    argv, ros_args = split_ros_args(sys.argv[1:] if argv is None else argv)
    args = p.parse_args(argv)
    args.ros_args = ros_args
    why = unavailable_reason()
    if why is not None:
        print(f"jaxrobo ros policy: {why}", file=sys.stderr)
        return 2
    return run(args)


def run(args) -> int:
    line_buffered()
    try:
        node = PolicyNode(args.export_dir, args.topics, args.ros_args)
    except SetupError as err:
        print(f"jaxrobo ros policy: {err}; nothing was started", file=sys.stderr)
        return 2
    stopping = stop_on_signals()
    try:
        node.start()
    except SetupError as err:
        print(f"jaxrobo ros policy: {err}", file=sys.stderr)
        return 2
    meta = node.policy.meta
    print(f"jaxrobo ros policy: {meta['env_id']} ({meta['kind']}) as {node.rospy.get_name()} every "
          f"{node.b.period:g} s of stamp time on {node.pub.resolved_name}", flush=True)
    while not stopping and not node.rospy.is_shutdown() and node.master_lost is None:
        node.watch()
        time.sleep(0.02)  # a signal's handler runs during the sleep; the loop stops after it
    node.stop()
    if node.master_lost is not None:
        print(f"jaxrobo ros policy: stopped the robot (zero command): {node.master_lost}", file=sys.stderr)
    s = node.stats()
    if args.stats:
        with open(args.stats, "w") as f:
            json.dump(s, f)
    print(f"jaxrobo ros policy: {s['commands']} commands, latency median {s['latency_ms']['median']} ms",
          flush=True)
    node.rospy.signal_shutdown("done")
    return 0 if node.master_lost is None else EXIT_MASTER_LOST


if __name__ == "__main__":
    sys.exit(main())
