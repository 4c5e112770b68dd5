"""``jaxrobo ros`` end to end on localhost (docs/ros.md): a master on a free port, the sim node, the policy node.

* a trained QuadcopterGoto-v2 table reaches its goals through ROS at the rate it reaches them in-process
  (the native port with the same numpy runner, on the same resets): within 2 percentage points;
* a cart-pole table keeps the pole up through ROS (the policy node, and the Gymnasium env over ROS) exactly as long
  as in-process from the same initial states;
* faults: the sim killed mid-episode, a sensor that stops, a NaN in a message, an export of another task, topics of
  another task: the policy node stops the robot (zero command) and says why; no traceback;
* the seed-style example (examples/ros/cartpole_qlearn.py) against a lockstep sim node sees the episodes it sees
  with the sim's model in its own process (``--local``), and its learner improves on average over 16 seeds.

Skipped, with the reason, where rospy or roscore is missing (``apt-get install ros-core python3-rospy ...``)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from jaxrobo_ros.system import unavailable_reason

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REASON = unavailable_reason() or (None if shutil.which("roscore") else "roscore is not on PATH: apt-get install "
                                  "ros-core (docs/ros.md)")
needs_ros = pytest.mark.skipif(REASON is not None, reason=f"ROS 1 missing: {REASON}")
pytestmark = pytest.mark.filterwarnings("ignore:notifyAll:DeprecationWarning")  # inside rospy
#: Wall-clock bound on any one node or script (the whole module runs in about a minute and a half on 2 cores).
BOUND = 240


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Ros:
    """A master on localhost, the nodes started from it (each in its own process group) and an in-process rospy."""

    def __init__(self, tmp):
        from jaxrobo.ros.launch import ros_env, start_master

        self.tmp, self.procs, port = tmp, [], free_port()
        self.env = ros_env(port)
        self.env.update(ROS_HOSTNAME="127.0.0.1", ROS_LOG_DIR=str(tmp / "log"), ROS_HOME=str(tmp),
                        JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
        self.saved = {k: os.environ.get(k) for k in ("ROS_MASTER_URI", "ROS_HOSTNAME", "ROS_LOG_DIR", "ROS_HOME")}
        os.environ.update({k: self.env[k] for k in self.saved})
        self.master = start_master(port, self.env)

    def node(self, *args, name: str, env: dict | None = None) -> subprocess.Popen:
        out = open(self.tmp / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "jaxrobo.cli", "ros", *args], env=env or self.env, stdout=out,
                             stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT)
        p.log = self.tmp / f"{name}.log"
        self.procs.append(p)
        return p

    def policy(self, *args, name: str) -> subprocess.Popen:
        """The policy node as it runs on a robot: ``python -m jaxrobo_ros.policy_node`` (no JAX)."""
        out = open(self.tmp / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "jaxrobo_ros.policy_node", *args], env=self.env, stdout=out,
                             stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT)
        p.log = self.tmp / f"{name}.log"
        self.procs.append(p)
        return p

    def script(self, *args) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, *args], env=self.env, capture_output=True, text=True, timeout=BOUND,
                              cwd=ROOT)

    def close(self):
        from jaxrobo.ros.launch import stop

        stop(self.procs + [self.master])
        for k, v in self.saved.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)


@pytest.fixture(scope="module")
def ros(tmp_path_factory):
    r = Ros(tmp_path_factory.mktemp("ros"))
    try:
        from jaxrobo_ros.system import rospy

        rospy().init_node("jaxrobo_test", anonymous=True, disable_signals=True)
        yield r
    finally:
        r.close()


def close(*things):
    """A test's teardown, in one call: its node processes stopped (:func:`jaxrobo.ros.launch.stop`), then its own
    handles dropped in the order given: a :class:`Listener`'s subscriber, a publisher, a service."""
    from jaxrobo.ros.launch import stop

    stop([t for t in things if isinstance(t, subprocess.Popen)])
    for t in things:
        if isinstance(t, Listener):
            t.sub.unregister()
        elif hasattr(t, "unregister"):  # a publisher or subscriber
            t.unregister()
        elif not isinstance(t, subprocess.Popen):  # a service
            t.shutdown()


def eventually(predicate, timeout=BOUND, every=0.05) -> bool:
    """Whether ``predicate()`` holds within ``timeout`` seconds: a node's log line is written after the message
    it reacts to, and the watchdog's zero commands count among the messages a test waits for."""
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            return False
        time.sleep(every)
    return True


def log(p) -> str:
    return p.log.read_text()


def train_export(tmp, env_id, *flags) -> str:
    from jaxrobo.cli import main

    run, out = str(tmp / "run"), str(tmp / "export")
    assert main(["train", "--env", env_id, "--seed", "0", "--no-progress", "--out", run, *flags]) == 0
    assert main(["export", run, "--out", out]) == 0
    return out


@pytest.fixture(scope="module")
def goto_export(tmp_path_factory):
    """The default ``jaxrobo train --env QuadcopterGoto-v2`` (it stops once its learning target holds), exported."""
    return train_export(tmp_path_factory.mktemp("goto"), "QuadcopterGoto-v2")


@pytest.fixture(scope="module")
def cartpole_export(tmp_path_factory):
    return train_export(tmp_path_factory.mktemp("cartpole"), "CartPoleStayUp-v0", "--n-envs", "16",
                        "--nepisodes", "60", "--set", "env.max_episode_steps=150", "--set", "nsteps=150",
                        "--set", "eval_envs=4")


def in_process(export: str, n: int, seed: int, first: int = 0) -> list[dict]:
    """Episodes ``first .. first + n - 1`` of key ``seed`` in-process: the native port and the numpy runner."""
    from jaxrobo.interop.numpy_policy import Policy
    from jaxrobo.ros.bridge import make_bridge, make_env
    from jaxrobo.ros.sim_node import episode_starts

    policy = Policy.load(export)
    env = make_env(policy.meta)
    port = make_bridge(env).port  # the port the sim node steps
    qpos, qvel, tasks = episode_starts(env, first + n, seed)
    return [port.episode(policy, qpos[i], qvel[i], tasks[i]) for i in range(first, first + n)]


def jax_episodes(export: str, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The JAX task's own return and length of episodes ``0 .. n - 1`` of key ``seed`` (the sim's resets), driven
    by the export's runner on the JAX observations (all ``n`` at once)."""
    import jax

    from jaxrobo.interop.numpy_policy import Policy
    from jaxrobo.ros.bridge import make_env
    from jaxrobo.task.rollout import rollout_start

    policy = Policy.load(export)
    env = make_env(policy.meta)
    state = jax.jit(lambda k: rollout_start(env, k, n)["first"])(jax.random.key(seed))
    step = jax.jit(jax.vmap(env.step))
    ret, length, alive = np.zeros(n), np.zeros(n, int), np.ones(n, bool)
    for _ in range(int(env.default_params.max_episode_steps)):
        state = step(state, policy.batch(np.asarray(state.obs)))
        ret += np.where(alive, np.asarray(state.reward, np.float64), 0.0)
        length += alive
        alive &= ~np.asarray(state.done)
        if not alive.any():
            break
    return ret, length


class Listener:
    """The commands a node publishes, as they arrive."""

    def __init__(self, topic, cls):
        from jaxrobo_ros.system import rospy

        self.got, self.cv = [], threading.Condition()
        self.sub = rospy().Subscriber(topic, cls, self._on, queue_size=100)

    def _on(self, msg):
        with self.cv:
            self.got.append(msg)
            self.cv.notify_all()

    def connected_to(self, uri: str, timeout=BOUND) -> bool:
        """Whether the publisher of node ``uri`` (:func:`node_uri`) has connected to this subscriber, on both ends:
        rospy connects in the background, a message published before the connection is not delivered, and another
        node's connection (a node of an earlier test still shutting down) says nothing of this one's. This end
        lists the connection a moment before the publisher's does (rospy's publisher adds it after writing its
        header), and a message the node publishes in between is lost: so the node's own list (its ``getBusInfo``,
        the connections its publisher writes to) must hold it too."""
        from xmlrpc.client import ServerProxy

        from jaxrobo_ros.system import rospy

        me, topic = rospy().get_caller_id(), self.sub.resolved_name

        def publishing() -> bool:
            try:
                info = ServerProxy(uri).getBusInfo(me)[2]
            except Exception:  # the node is going, or not serving yet
                return False
            return any(c[1] == me and c[2] == "o" and c[4] == topic for c in info)

        return linked(self.sub, uri, timeout) and eventually(publishing, timeout, every=0.01)

    def wait(self, n, timeout=30.0):
        end = time.monotonic() + timeout
        with self.cv:
            while len(self.got) < n and time.monotonic() < end:
                self.cv.wait(0.05)
        return len(self.got) >= n


def node_uri(proc, name: str, timeout=BOUND) -> str:
    """The XML-RPC URI of the ROS node ``name`` that process ``proc`` runs, once it has registered with the master
    (the master may still list a node of the same name from an earlier test: its pid tells them apart)."""
    from xmlrpc.client import ServerProxy

    import rosgraph

    master = rosgraph.Master("/jaxrobo_test_lookup")
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            uri = master.lookupNode(name)
            if ServerProxy(uri).getPid("/jaxrobo_test_lookup")[2] == proc.pid:
                return uri
        except Exception:  # not registered yet, or the URI of a node that has gone
            pass
        time.sleep(0.05)
    raise AssertionError(f"node {name} (pid {proc.pid}) did not register within {timeout} s:\n{log(proc)}")


def subscribed_by(pub, caller_id: str, timeout=BOUND) -> bool:
    """Whether node ``caller_id`` has connected to the publisher ``pub`` of this process: another subscriber (this
    process's own, an earlier test's node) connected first says nothing of it."""
    return linked(pub, caller_id, timeout)


def linked(end_of_topic, endpoint: str, timeout=BOUND) -> bool:
    """Whether a connection of this process's publisher or subscriber ``end_of_topic`` comes from ``endpoint`` (a
    node's caller id or URI) within ``timeout`` seconds."""
    return eventually(lambda: any(getattr(c, "endpoint_id", None) == endpoint
                                  for c in list(end_of_topic.impl.connections or ())), timeout, every=0.01)


@needs_ros
def test_policy_node_imports_no_jax(goto_export, cartpole_export):
    """The policy node from an export: its module, the export's runner and robot section, rospy; no JAX, no task
    module, no MuJoCo, not even jaxrobo's package (a robot's computer needs none of it)."""
    code = ("import json, sys\n"
            "from jaxrobo_ros.policy_node import PolicyNode\n"
            "nodes = [PolicyNode(d) for d in sys.argv[1:]]\n"
            "print(json.dumps({'periods': [n.b.period for n in nodes], 'loaded': sorted(m for m in sys.modules if "
            "m.split('.')[0] in ('jax', 'jaxlib', 'mujoco', 'jaxrobo', 'envs', 'brax', 'flax'))}))")
    r = subprocess.run([sys.executable, "-c", code, goto_export, cartpole_export], capture_output=True, text=True,
                       timeout=BOUND, cwd=ROOT, env=dict(os.environ, PYTHONPATH=ROOT))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["loaded"] == [], out
    assert out["periods"] == pytest.approx([0.3, 0.04])  # the tasks' running_step, from the exports


@pytest.mark.slow
@needs_ros
def test_goto_through_ros_arrives_as_in_process(ros, goto_export):
    from jaxrobo.ros.msgs import RLExperimentInfo

    n, seed = 50, 7
    results, stats = ros.tmp / "goto_results.json", ros.tmp / "goto_stats.json"
    rewards = Listener("/openai/reward", RLExperimentInfo)
    sim = ros.node("sim", goto_export, "--episodes", str(n), "--lockstep", "--seed", str(seed), "--results",
                   str(results), name="goto_sim")
    # In lockstep no episode ends before the policy node answers: starting it once the sim's /openai/reward has
    # reached this listener keeps the first episode's message (one CI run on a loaded machine lost it)
    assert rewards.connected_to(node_uri(sim, "/jaxrobo_sim")), log(sim)
    policy = ros.policy(goto_export, "--stats", str(stats), name="goto_policy")
    try:
        assert sim.wait(timeout=BOUND) == 0, log(sim)
        assert rewards.wait(n, timeout=10)
    finally:
        close(sim, policy, rewards)
    eps = json.loads(results.read_text())["episodes"]
    native = in_process(goto_export, n, seed)
    rate_ros = np.mean([e["success"] for e in eps])
    rate_native = np.mean([e["success"] for e in native])
    assert len(eps) == n
    assert rate_ros >= 0.9, rate_ros  # the trained policy reaches its goals through ROS
    assert abs(rate_ros - rate_native) <= 0.02, (rate_ros, rate_native)
    # lockstep: the same flights, step for step, but for the first episode: one CI run flew it one step longer
    # through ROS (42 against 41) and every later episode identically; the two nodes' start-up is not in lockstep
    apart = [(i, e["steps"], f["length"]) for i, (e, f) in enumerate(zip(eps, native)) if e["steps"] != f["length"]]
    assert all(i == 0 and abs(a - b) <= 1 for i, a, b in apart), apart
    # every state the sim published was answered by one command
    s = json.loads(stats.read_text())
    assert s["commands"] == sum(e["steps"] for e in eps), (s, sum(e["steps"] for e in eps))
    assert "Traceback" not in log(policy) + log(sim)
    # /openai/reward: each episode's shaped return as the JAX task computes it (float32 steps there), on every
    # episode flown for as many steps as in JAX (the two engines agree to float32 round-off: where a rounding
    # flips a bin, the flights part)
    assert [m.episode_number for m in rewards.got] == [e["episode"] for e in eps]
    sent = np.array([m.episode_reward for m in rewards.got])
    assert np.allclose(sent, [e["reward"] for e in eps], rtol=1e-6, atol=1e-4)  # the message is float32
    ret, length = jax_episodes(goto_export, n, seed)
    same = np.array([e["steps"] for e in eps]) == length
    assert same.mean() >= 0.9, (length, [e["steps"] for e in eps])
    assert np.allclose(sent[same], ret[same], rtol=1e-4, atol=1e-3), np.c_[sent, ret, same]
    assert len(set(np.round(sent, 3))) > 1  # shaped returns, not an arrival flag


@pytest.mark.slow
@needs_ros
def test_cartpole_through_ros_stays_up_as_in_process(ros, cartpole_export):
    n, seed = 4, 3
    results = ros.tmp / "cp_results.json"
    sim = ros.node("sim", cartpole_export, "--episodes", str(n), "--lockstep", "--seed", str(seed), "--results",
                   str(results), name="cp_sim")
    policy = ros.policy(cartpole_export, name="cp_policy")
    try:
        assert sim.wait(timeout=BOUND) == 0, log(sim)
    finally:
        close(sim, policy)
    eps = json.loads(results.read_text())["episodes"]
    native = in_process(cartpole_export, n, seed)
    assert [e["steps"] for e in eps] == [e["length"] for e in native]
    assert "Traceback" not in log(policy) + log(sim)


def subscribers(topic: str) -> list[str]:
    """The nodes the master lists as subscribers of ``topic``."""
    import rosgraph

    _, subs, _ = rosgraph.Master("/jaxrobo_test_lookup").getSystemState()
    return next((nodes for t, nodes in subs if t == topic), [])


@needs_ros
def test_lockstep_sim_steps_once_per_state_when_an_answer_comes_twice(ros, cartpole_export):
    """A late answer, not a lost one: the lockstep sim republishes a state it has no command for after REPUBLISH s,
    the policy node answers the state seen again with its command again, and the sim receives two answers to one
    state (a fresh clone under load once flew its roslaunch episodes with one command counted twice). The command
    topics carry no stamp; the policy node sends each command again stamped with the state it answers, and the sim
    steps each state once, on the copy stamped with it. Here this test answers the sim's states as the policy node
    does (plain and stamped) and sends its answer to one state a second time once the sim has stepped that state:
    the sim does not step on it, and flies the in-process episode state for state. No timing decides the outcome:
    the second answer goes out after the sim has published the next state."""
    from sensor_msgs.msg import JointState

    from jaxrobo.ros.sim_node import REPUBLISH
    from jaxrobo_ros.bridge import make_bridge
    from jaxrobo_ros.policy_node import load_export
    from jaxrobo_ros.system import rospy as get

    rospy = get()
    seed, again = 4, 5  # the answer to state 5 (the sixth) goes out twice
    policy = load_export(cartpole_export)
    b = make_bridge(policy.io)
    top = b.topics
    results = ros.tmp / "twice_results.json"
    states = Listener(top["joint_states"], JointState)
    plain = rospy.Publisher(top["command"], b.msg_types()["command"], queue_size=10)
    stamped = rospy.Publisher(top["command_stamped"], b.stamped_type(), queue_size=10)
    sim = ros.node("sim", cartpole_export, "--episodes", "1", "--lockstep", "--seed", str(seed), "--results",
                   str(results), name="twice_sim")
    seen = []  # the observation of each state answered
    try:
        assert states.connected_to(node_uri(sim, "/jaxrobo_sim")), log(sim)
        # this test's answers reach the sim on each command topic it takes them from (it subscribes to the stamped
        # copies before the plain commands: once it is on the one, the master lists it on the other)
        assert subscribed_by(plain, "/jaxrobo_sim"), log(sim)
        if "/jaxrobo_sim" in subscribers(top["command_stamped"]):
            assert subscribed_by(stamped, "/jaxrobo_sim"), log(sim)

        def state(i):
            """The i-th state message received, once it is there; None once the sim has ended without it."""
            while not states.wait(i + 1, timeout=0.1):
                if sim.poll() is not None:
                    return None
            return states.got[i]

        i, last = 0, None
        while (msg := state(i)) is not None:
            i += 1
            if last is not None and msg.header.stamp <= last:
                continue  # the same state republished: its answer is on its way
            last = msg.header.stamp
            obs = b.observation({"joint_states": msg})
            out = b.command_msg(policy(obs))
            copy = b.stamped_command(out, last)
            plain.publish(out)
            stamped.publish(copy)
            seen.append(obs)
            if len(seen) == again + 1:
                # once the sim has stepped this state (its next one is out), the same answer again: what the policy
                # node sends when its first answer was late and the sim republished the state meanwhile
                assert eventually(lambda: any(m.header.stamp > last for m in states.got[i:]), timeout=60), log(sim)
                plain.publish(out)
                stamped.publish(copy)
                time.sleep(2 * REPUBLISH)
                newer = {m.header.stamp.to_nsec() for m in states.got[i:] if m.header.stamp > last}
                assert len(newer) == 1, f"the sim stepped on a second answer to one state:\n{log(sim)}"
        assert sim.wait(timeout=BOUND) == 0, log(sim)
    finally:
        close(sim, states, plain, stamped)
    native = in_process(cartpole_export, 1, seed)[0]
    eps = json.loads(results.read_text())["episodes"]
    assert len(seen) > again + 1
    assert [e["steps"] for e in eps] == [native["length"]] == [len(seen)], (eps, native["length"], len(seen))
    assert np.array_equal(np.asarray(seen), native["obs"][:len(seen)])  # the same states, the same answers
    assert "dropped 1 late or repeated answer " in log(sim), log(sim)
    assert "Traceback" not in log(sim)


@needs_ros
def test_policy_node_answers_a_state_seen_again_with_the_same_stamped_command(cartpole_export):
    """The policy node's side of lockstep: each command goes out plain and again stamped with the state it answers
    (the primary reading's stamp); the same state seen again (republished by a sim that has no command for it) is
    answered with the same two messages; the watchdog's zero command answers no state and is not stamped."""
    from types import SimpleNamespace

    from sensor_msgs.msg import JointState

    from jaxrobo_ros.policy_node import PolicyNode
    from jaxrobo_ros.system import rospy as get

    node = PolicyNode(cartpole_export)
    plain, stamped = [], []
    node.pub, node.stamped_pub = SimpleNamespace(publish=plain.append), SimpleNamespace(publish=stamped.append)

    def joints(t, pole):
        m = JointState(name=["foot_joint", "pole_joint"], position=[0.01, pole], velocity=[0.1, -0.2])
        m.header.stamp = get().Time.from_sec(t)
        return m

    for t, pole in ((2.0, 0.02), (2.0, 0.02), (2.04, -0.05)):
        node._on_msg(joints(t, pole), "joint_states")
    assert node.commands == 2  # two states answered; the second message was the first state again
    assert len(plain) == len(stamped) == 3
    assert plain[1] is plain[0] and stamped[1] is stamped[0]  # the same answer again, both copies
    assert [m.header.stamp.to_sec() for m in stamped] == pytest.approx([2.0, 2.0, 2.04], abs=1e-9)
    assert [(m.name, list(m.velocity)) for m in stamped] == [(["foot_joint"], [p.data]) for p in plain]
    node._hold("a test")
    assert len(stamped) == 3 and len(plain) == 4 and plain[-1].data == 0.0
    # Stopping sends the zero command last: a reading that arrives after it (rospy's callback threads run until
    # the shutdown closes the topics) sends nothing, where a publish to a closed topic would raise in the callback.
    node.rospy = SimpleNamespace(Publisher=None)
    node.stop()
    assert node.closing and len(plain) == 5 and plain[-1].data == 0.0
    node._on_msg(joints(2.08, 0.1), "joint_states")
    assert len(plain) == 5 and len(stamped) == 3 and node.commands == 2


@needs_ros
def test_policy_node_names_the_episode_each_stamped_answer_counts_from(cartpole_export):
    """A new episode's first state can reach the policy node before the episode's number: ``/jaxrobo/episode`` and
    the states travel over separate connections, and the sim's EPISODE_MARGIN only makes it rare (a benchmark run on
    shared cores flew one lockstep cart-pole episode of 20 for another number of steps than native; with no margin
    and a loaded CPU it happened in one run of three). Answered then, the state gets a command counted from the last
    episode's accumulated cart command. The stamped copy names the episode the node had heard of (header.frame_id),
    so a lockstep sim does not step on it; the number (a Header: the episode's start stamp with it) brings the state
    an answer afresh, from the number's callback, as a node that heard of the episode in time answers it, and the
    state again gets that answer again."""
    from types import SimpleNamespace

    from sensor_msgs.msg import JointState

    from jaxrobo_ros.bridge import tagged_episode
    from jaxrobo_ros.policy_node import PolicyNode
    from jaxrobo_ros.system import rospy as get

    def node():
        n = PolicyNode(cartpole_export)
        n.plain, n.stamped = [], []
        n.pub, n.stamped_pub = SimpleNamespace(publish=n.plain.append), SimpleNamespace(publish=n.stamped.append)
        return n

    def joints(t, pole):
        m = JointState(name=["foot_joint", "pole_joint"], position=[0.01, pole], velocity=[0.1, -0.2])
        m.header.stamp = get().Time.from_sec(t)
        return m

    late, in_time = node(), node()
    late._on_msg(episode_header(0, 2.0), "episode")
    for k, pole in enumerate((0.05, 0.05, 0.05, 0.05, 0.05, 0.05)):  # episode 0: the cart command accumulates
        late._on_msg(joints(2.0 + 0.04 * k, pole), "joint_states")
    assert late.commands == 6 and late.b.command != late.b.start
    assert {tagged_episode(m) for m in late.stamped} == {0}
    first = joints(2.4, -0.03)  # episode 1's first state, before its number
    late._on_msg(first, "joint_states")
    stale = late.stamped[-1]
    assert tagged_episode(stale) == 0  # counted from episode 0's command: a lockstep sim drops it
    late._on_msg(episode_header(1, 2.4), "episode")
    assert late.commands == 8 and late.stamped[-1] is not stale and tagged_episode(late.stamped[-1]) == 1
    answer = late.stamped[-1]
    late._on_msg(first, "joint_states")  # the sim republishes a state it has no answer for: the same answer
    assert late.commands == 8 and late.stamped[-1] is answer

    in_time._on_msg(episode_header(0, 2.0), "episode")
    in_time._on_msg(episode_header(1, 2.4), "episode")
    in_time._on_msg(first, "joint_states")
    assert tagged_episode(in_time.stamped[-1]) == 1
    assert late.stamped[-1].velocity == in_time.stamped[-1].velocity and late.plain[-1] == in_time.plain[-1]
    assert stale.velocity != in_time.stamped[-1].velocity  # the stale answer was another command
    assert late.stamped[-1].header.stamp == stale.header.stamp == first.header.stamp


@needs_ros
def test_lockstep_sim_does_not_step_on_an_answer_of_another_episode(ros, cartpole_export):
    """The sim's side: a stamped answer to the state it waits on, but computed in another episode (header.frame_id
    names it), is dropped and the state republished; the answer of its own episode steps it, and the episode is the
    in-process one. No timing decides the outcome: the test waits for the republished state before answering."""
    from sensor_msgs.msg import JointState

    from jaxrobo.ros.sim_node import REPUBLISH
    from jaxrobo_ros.bridge import episode_tag, make_bridge
    from jaxrobo_ros.policy_node import load_export
    from jaxrobo_ros.system import rospy as get

    rospy = get()
    seed = 4
    policy = load_export(cartpole_export)
    b = make_bridge(policy.io)
    top = b.topics
    results = ros.tmp / "other_episode_results.json"
    states = Listener(top["joint_states"], JointState)
    stamped = rospy.Publisher(top["command_stamped"], b.stamped_type(), queue_size=10)
    sim = ros.node("sim", cartpole_export, "--episodes", "1", "--lockstep", "--seed", str(seed), "--results",
                   str(results), name="other_episode_sim")
    seen = []
    try:
        assert states.connected_to(node_uri(sim, "/jaxrobo_sim")), log(sim)
        assert subscribed_by(stamped, "/jaxrobo_sim"), log(sim)
        assert states.wait(1, timeout=60), log(sim)
        first = states.got[0]
        wrong = b.stamped_command(b.command_msg(policy(b.observation({"joint_states": first}))), first.header.stamp)
        wrong.header.frame_id = episode_tag(7)
        b.reset_memory()
        stamped.publish(wrong)
        # the sim republishes the first state (it has no answer of its own episode), and steps on nothing else
        assert states.wait(2, timeout=60), log(sim)
        time.sleep(REPUBLISH)
        assert all(m.header.stamp == first.header.stamp for m in states.got), log(sim)
        i, last = 0, None
        while True:
            while not states.wait(i + 1, timeout=0.1):
                if sim.poll() is not None:
                    break
            if len(states.got) <= i:
                break
            msg = states.got[i]
            i += 1
            if last is not None and msg.header.stamp <= last:
                continue  # the same state republished
            last = msg.header.stamp
            obs = b.observation({"joint_states": msg})
            copy = b.stamped_command(b.command_msg(policy(obs)), last)
            copy.header.frame_id = episode_tag(0)
            stamped.publish(copy)
            seen.append(obs)
        assert sim.wait(timeout=BOUND) == 0, log(sim)
    finally:
        close(sim, states, stamped)
    native = in_process(cartpole_export, 1, seed)[0]
    eps = json.loads(results.read_text())["episodes"]
    assert [e["steps"] for e in eps] == [native["length"]] == [len(seen)], (eps, native["length"], len(seen))
    assert np.array_equal(np.asarray(seen), native["obs"][:len(seen)])
    assert "dropped 1 late or repeated answer " in log(sim), log(sim)
    assert "Traceback" not in log(sim)


def drone_state(t: float, pos=(0.5, -0.3, 1.0), yaw=0.3, sonar=3.0) -> dict:
    """One moment's drone readings stamped ``t`` (the odometry and the four sonars), by topic key."""
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Range

    from jaxrobo_ros.bridge import SONARS
    from jaxrobo_ros.system import rospy

    when = rospy().Time.from_sec(t)
    o = Odometry()
    o.header.stamp = when
    o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z = pos
    o.pose.pose.orientation.w, o.pose.pose.orientation.z = np.cos(yaw / 2), np.sin(yaw / 2)
    out = {}
    for name in SONARS:
        out[name] = Range(range=sonar)
        out[name].header.stamp = when
    return {**out, "odom": o}  # the odometry last: the reading the policy node acts on


def episode_header(episode: int, t: float):
    """``/jaxrobo/episode`` as the sim publishes it: episode ``episode``, started at ``t`` (its first state's
    stamp)."""
    from jaxrobo_ros.bridge import episode_msg
    from jaxrobo_ros.system import rospy

    return episode_msg(episode, rospy().Time.from_sec(t))


def drone_episode(episode, goal, t: float, rows=((0, 1.0, 1.5, 1.0, 0.3, 0.3, 1.0),)) -> dict:
    """An episode's goal (frame ``world``, stamped ``t``: its first state's, the episode's start) and obstacles,
    naming ``episode`` as the sim names them (None: naming none, as an older sender's: without a layout)."""
    from geometry_msgs.msg import PointStamped
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension

    from jaxrobo_ros.bridge import episode_tag
    from jaxrobo_ros.system import rospy

    g = PointStamped()
    g.header.stamp, g.header.frame_id = rospy().Time.from_sec(t), "world"
    g.point.x, g.point.y, g.point.z = goal
    o = Float64MultiArray(data=[float(x) for r in rows for x in r])
    if episode is not None:
        o.layout.dim = [MultiArrayDimension(label=episode_tag(episode), size=len(rows), stride=7 * len(rows))]
    return {"goal": g, "obstacles": o}


def drone_node(export: str):
    """A policy node of the drone whose commands (plain and stamped) and observations are kept, not published."""
    from types import SimpleNamespace

    from jaxrobo_ros.policy_node import PolicyNode

    n = PolicyNode(export)
    n.plain, n.stamped, n.seen, runner = [], [], [], n.policy
    n.pub, n.stamped_pub = SimpleNamespace(publish=n.plain.append), SimpleNamespace(publish=n.stamped.append)
    n.policy = lambda obs: (n.seen.append(np.asarray(obs)), runner(obs))[1]
    return n


def feed(node, msgs: dict) -> None:
    for name, m in msgs.items():
        node._on_msg(m, name)


@needs_ros
def test_drone_node_waits_for_its_episodes_goal_and_obstacles(goto_export):
    """A new episode's goal and obstacles travel over connections of their own and can reach the policy node after
    the episode's number and first state (the sim's EPISODE_MARGIN only makes it rare). The goal is stamped with its
    episode's start, which /jaxrobo/episode carries, and the obstacle array names its episode
    (layout.dim[0].label): the node does not act on a state of episode 1 with episode 0's goal or obstacles; it
    holds the state and acts from the callback of the message that completes the set, as a node that had them in
    time. A first state that came before its episode's number (stamped from the start the number carries) is acted
    on when the number comes, not dropped."""
    from jaxrobo_ros.bridge import Fault, tagged_episode

    node, in_time = drone_node(goto_export), drone_node(goto_export)
    node._on_msg(episode_header(0, 1.0), "episode")
    feed(node, drone_episode(0, (2.0, -1.0, 1.2), 1.0))
    feed(node, drone_state(1.0))
    assert node.commands == 1 and tagged_episode(node.stamped[-1]) == 0
    # episode 1: its number and first state, while episode 0's goal and obstacles are still the node's
    node._on_msg(episode_header(1, 1.5), "episode")
    first = drone_state(1.5, pos=(-0.2, 0.4, 0.9), yaw=-1.0, sonar=2.5)
    feed(node, first)
    assert node.commands == 1 and len(node.stamped) == len(node.plain) == 1  # waits: no command, not a zero one
    with pytest.raises(Fault, match="/drone/goal: stamped 1.000 s, not of the current episode "
                                    r"\(episode 1, started at 1.500 s") as err:
        node.b.observation(node.latest)
    assert err.value.waiting
    new = drone_episode(1, (-1.5, 2.0, 0.8), 1.5, rows=((1, -0.5, 1.0, 1.0, 0.4, 0.2, 1.0),))
    node._on_msg(new["goal"], "goal")
    assert node.commands == 1  # episode 0's obstacles are not taken either
    with pytest.raises(Fault, match="/jaxrobo/obstacles: of episode 0, not of the current episode") as err:
        node.b.observation(node.latest)
    assert err.value.waiting
    node._on_msg(new["obstacles"], "obstacles")
    assert node.commands == 2  # at once, from the obstacles' callback, on the state held
    assert tagged_episode(node.stamped[-1]) == 1 and node.stamped[-1].header.stamp == first["odom"].header.stamp

    in_time._on_msg(episode_header(1, 1.5), "episode")
    feed(in_time, new)
    feed(in_time, first)
    assert in_time.commands == 1 and np.array_equal(node.seen[-1], in_time.seen[-1])
    assert node.stamped[-1].twist == in_time.stamped[-1].twist
    # what the node would have acted on with episode 0's goal and obstacles (taken as a sender's that numbers no
    # episodes: no number heard)
    unnumbered = {k: m for k, m in node.latest.items() if k != "episode"}
    stale = node.b.observation({**unnumbered, **drone_episode(None, (2.0, -1.0, 1.2), 1.0)})
    assert not np.array_equal(stale, node.seen[-1])

    # episode 2: goal and obstacles, then the first state before the episode's number: held, acted on at the number
    feed(node, drone_episode(2, (1.0, 1.0, 1.5), 2.0))
    second = drone_state(2.0, pos=(0.1, 0.1, 1.1))
    feed(node, second)
    assert node.commands == 2
    node._on_msg(episode_header(2, 2.0), "episode")
    assert node.commands == 3 and tagged_episode(node.stamped[-1]) == 2
    assert node.stamped[-1].header.stamp == second["odom"].header.stamp


@needs_ros
def test_drone_goal_belongs_to_the_episode_of_its_stamp(goto_export):
    """The goal (frame world) belongs to the episode whose start it is stamped with; heard with no /jaxrobo/episode
    (Gazebo, a robot: nothing numbers episodes) it is current. Obstacles naming no episode (an older sender's) count
    in every episode; obstacles naming one, in that one alone. A goal of the sim's, which numbers its episodes,
    brings that episode's obstacles."""
    from jaxrobo_ros.bridge import Bridge, Fault, episode_tag, tagged_episode

    plain, named = drone_episode(None, (2.0, -1.0, 1.2), 0.0), drone_episode(4, (2.0, -1.0, 1.2), 0.0)
    assert plain["goal"].header.frame_id == named["goal"].header.frame_id == "world"
    assert tagged_episode(named["goal"]) is None  # the goal's frame_id is its frame, not a tag
    assert Bridge.episode_check(named["goal"], None) and Bridge.episode_check(named["goal"], episode_header(4, 0.0))
    assert Bridge.episode_check(named["goal"], episode_header(3, 0.0))  # the stamp, not a number, says its episode
    assert not Bridge.episode_check(named["goal"], episode_header(4, 0.3))
    assert tagged_episode(plain["obstacles"]) is None
    assert all(Bridge.episode_check(plain["obstacles"], e) for e in (None, episode_header(0, 0.0),
                                                                       episode_header(4, 0.3)))
    assert tagged_episode(named["obstacles"]) == 4 and Bridge.episode_check(named["obstacles"], episode_header(4, 1))
    assert not Bridge.episode_check(named["obstacles"], episode_header(3, 1))
    assert not Bridge.episode_check(named["obstacles"], None)

    node = drone_node(goto_export)
    node._on_msg(plain["goal"], "goal")  # no obstacles topic at all: an empty map, as before
    feed(node, drone_state(1.0))
    assert node.commands == 1 and node.stamped[-1].header.frame_id == ""  # no episode heard: none named
    node._on_msg(plain["obstacles"], "obstacles")
    for k, episode in enumerate((3, 4)):
        t = 1.0 + node.b.period * (k + 1)  # the next control periods
        node._on_msg(episode_header(episode, t), "episode")
        feed(node, drone_state(t))
        assert node.commands == 1 + k  # the goal held is stamped with another episode's start: waits
        with pytest.raises(Fault, match="/drone/goal: stamped .* not of the current episode") as err:
            node.b.current(node.latest)
        assert err.value.waiting
        node._on_msg(drone_episode(None, (2.0, -1.0, 1.2), t)["goal"], "goal")  # plain obstacles count in each
        assert node.commands == 2 + k and node.stamped[-1].header.frame_id == episode_tag(episode)

    fresh = drone_node(goto_export)
    fresh._on_msg(episode_header(4, 0.0), "episode")
    fresh._on_msg(named["goal"], "goal")
    feed(fresh, drone_state(1.0))
    assert fresh.commands == 0
    with pytest.raises(Fault, match="no message yet for episode 4"):
        fresh.b.observation(fresh.latest)
    fresh._on_msg(named["obstacles"], "obstacles")
    assert fresh.commands == 1


@needs_ros
def test_drone_node_over_ros_acts_once_its_episodes_goal_and_obstacles_arrive(ros, goto_export):
    """The same over a master, the policy node in its own process: a state of episode 5 whose obstacles have not
    come (the last episode's are still latched) gets no answer, whatever order the node hears the episode's number,
    goal and state in (before the number the goal is not of the node's episode, after it the obstacles are not); it
    is answered, once, stamped with it and naming its episode, when they come. The state is sent once (no sim
    republishes it here), so the answer is the node's to the state it held. /jaxrobo/episode (a std_msgs/Header)
    arrives with the seq it was sent with: rospy numbers the messages that have a header, not a Header itself (5 is
    not the count rospy would write: this publisher's first message)."""
    from geometry_msgs.msg import PointStamped, TwistStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Range
    from std_msgs.msg import Float64MultiArray, Header

    from jaxrobo_ros.bridge import SONARS, load_topics, tagged_episode
    from jaxrobo_ros.system import rospy as get

    rospy = get()
    top = load_topics("quadcopter")["topics"]
    types = {"odom": Odometry, "goal": PointStamped, "obstacles": Float64MultiArray, "episode": Header,
             **{s: Range for s in SONARS}}
    pubs = {k: rospy.Publisher(top[k], cls, queue_size=10, latch=k in ("goal", "obstacles", "episode"))
            for k, cls in types.items()}
    new = drone_episode(5, (-1.5, 2.0, 0.8), 1.5, rows=((1, -0.5, 1.0, 1.0, 0.4, 0.2, 1.0),))
    pubs["episode"].publish(episode_header(5, 1.5))
    pubs["goal"].publish(new["goal"])
    pubs["obstacles"].publish(drone_episode(4, (2.0, -1.0, 1.2), 1.0)["obstacles"])
    answers = Listener(top["command_stamped"], TwistStamped)
    episodes = Listener(top["episode"], Header)
    policy = ros.policy(goto_export, name="episode_goal_policy")
    try:
        assert answers.connected_to(node_uri(policy, "/jaxrobo_policy")), log(policy)
        assert all(subscribed_by(p, "/jaxrobo_policy") for p in pubs.values()), log(policy)
        first = drone_state(1.5, pos=(-0.2, 0.4, 0.9))
        for k, m in first.items():
            pubs[k].publish(m)
        assert not answers.wait(1, timeout=1.0), (answers.got, log(policy))  # waits for episode 5's obstacles
        pubs["obstacles"].publish(new["obstacles"])
        assert answers.wait(1, timeout=30), log(policy)
        answer = answers.got[0]
        assert tagged_episode(answer) == 5 and answer.header.stamp == first["odom"].header.stamp
        assert not answers.wait(2, timeout=0.5)  # one answer to the one state
        assert episodes.wait(1), "the latched /jaxrobo/episode did not reach this process's subscriber"
        got = episodes.got[0]
        assert (got.seq, got.stamp, got.frame_id) == (5, new["goal"].header.stamp, "world"), got
    finally:
        close(policy, answers, episodes, *pubs.values())
    assert "Traceback" not in log(policy)


@needs_ros
def test_gym_env_over_ros_is_the_task(ros, cartpole_export):
    import gymnasium as gym

    from jaxrobo.interop.numpy_policy import Policy

    seed = 5
    sim = ros.node("sim", cartpole_export, "--lockstep", "--seed", str(seed), name="gym_sim")
    try:
        env = gym.make("jaxrobo-ros/CartPoleStayUp-v0", params={"max_episode_steps": 150}, timeout=60.0)
        policy = Policy.load(cartpole_export)
        lengths = []
        for _ in range(2):  # the sim starts at episode 0; each reset_simulation draws the next one
            obs, _ = env.reset()
            for t in range(1000):
                obs, reward, terminated, truncated, _ = env.step(policy(obs))
                assert reward == 1.0
                if terminated or truncated:
                    break
            lengths.append(t + 1)
        env.close()
    finally:
        close(sim)
    assert lengths == [e["length"] for e in in_process(cartpole_export, 2, seed, first=1)]


@needs_ros
def test_gym_env_over_ros_gives_the_drones_shaped_reward(ros, goto_export):
    """The drone through the Gymnasium env over ROS: each step's reward is the task's shaped one, so an episode's
    rewards sum to its return in-process (the native port, the same runner, the same resets) to float32 round-off
    (the observation and the sonar messages are float32). The sim's goal is in frame world and stamped with its
    episode's start, as /jaxrobo/episode (number and start) says; the last episode's goal is refused (waiting)."""
    import gymnasium as gym

    from jaxrobo.interop.numpy_policy import Policy

    from jaxrobo_ros.bridge import Fault, tagged_episode

    n, seed = 3, 11
    sim = ros.node("sim", goto_export, "--lockstep", "--seed", str(seed), name="gym_goto_sim")
    try:
        env = gym.make("jaxrobo-ros/QuadcopterGoto-v2", timeout=60.0)
        policy = Policy.load(goto_export)
        flights, last_goal = [], None
        for k in range(n):  # the sim starts at episode 0; each reset_simulation draws the next one
            obs, _ = env.reset()
            with env.unwrapped.cv:  # the env's subscribers write to it
                latest = dict(env.unwrapped.latest)
            goal, episode = latest["goal"], latest["episode"]
            assert goal.header.frame_id == "world" and episode.frame_id == "world"
            assert episode.seq == tagged_episode(latest["obstacles"]) == k + 1
            assert goal.header.stamp == episode.stamp == latest["odom"].header.stamp  # the episode's first state
            if last_goal is not None:
                with pytest.raises(Fault, match="/drone/goal: stamped .* not of the current episode") as err:
                    env.unwrapped.b.current({**latest, "goal": last_goal})
                assert err.value.waiting
            last_goal = goal
            rewards, info = [], {}
            for _ in range(1000):
                obs, reward, terminated, truncated, info = env.step(policy(obs))
                rewards.append(reward)
                if terminated or truncated:
                    break
            flights.append((rewards, info))
        env.close()
    finally:
        close(sim)
    assert "Traceback" not in log(sim)
    native = in_process(goto_export, n, seed, first=1)
    assert [len(r) for r, _ in flights] == [e["length"] for e in native]
    assert [i["arrived"] for _, i in flights] == [bool(e["success"]) for e in native]
    assert [i["crashed"] for _, i in flights] == [bool(e["crashed"]) for e in native]
    returns = [float(np.sum(r)) for r, _ in flights]
    assert np.allclose(returns, [e["return"] for e in native], rtol=1e-5, atol=1e-4), (returns, native)
    assert len({round(x, 4) for r, _ in flights for x in r}) > 3  # shaped per step, not an arrival flag


@needs_ros
def test_gym_env_over_ros_reset_waits_for_its_episodes_goal(ros, goto_export):
    """The Gymnasium env's reset, against a sim (here this test's, answering the /gazebo services) whose new goal
    and obstacles come after the new episode's number and first state: the reset returns that state with the new
    episode's goal and obstacles, once they have come, not with the last episode's."""
    import gymnasium as gym
    from geometry_msgs.msg import PointStamped, Twist
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Range
    from std_msgs.msg import Float64MultiArray, Header

    import jaxrobo.ros  # noqa: F401 - registers the envs
    from jaxrobo.ros import msgs
    from jaxrobo_ros.bridge import SONARS, load_topics, tagged_episode
    from jaxrobo_ros.system import rospy as get

    rospy = get()
    top = load_topics("quadcopter")["topics"]
    types = {"odom": Odometry, "goal": PointStamped, "obstacles": Float64MultiArray, "episode": Header,
             **{s: Range for s in SONARS}}
    pubs = {k: rospy.Publisher(top[k], cls, queue_size=10, latch=True) for k, cls in types.items()}
    commands = Listener(top["cmd_vel"], Twist)
    new = drone_episode(1, (-1.5, 2.0, 0.8), 1.5, rows=((1, -0.5, 1.0, 1.0, 0.4, 0.2, 1.0),))
    first = drone_state(1.5, pos=(-0.2, 0.4, 0.9), yaw=-1.0, sonar=2.5)
    sent = []

    def late_goal():
        time.sleep(0.5)
        sent.append(time.monotonic())
        for k, m in new.items():
            pubs[k].publish(m)

    def reset(_req):
        pubs["episode"].publish(episode_header(1, 1.5))
        for k, m in first.items():
            pubs[k].publish(m)
        threading.Thread(target=late_goal, daemon=True).start()
        return msgs.EmptyResponse()

    services = [rospy.Service(f"/gazebo/{name}", msgs.Empty, fn) for name, fn in
                (("pause_physics", lambda _r: msgs.EmptyResponse()),
                 ("unpause_physics", lambda _r: msgs.EmptyResponse()), ("reset_simulation", reset))]
    env = None
    try:
        pubs["episode"].publish(episode_header(0, 1.0))
        for k, m in {**drone_episode(0, (2.0, -1.0, 1.2), 1.0), **drone_state(1.0)}.items():
            pubs[k].publish(m)
        env = gym.make("jaxrobo-ros/QuadcopterGoto-v2", timeout=30.0)
        obs, _ = env.reset()
        done = time.monotonic()
        assert sent and done >= sent[0]
        latest = env.unwrapped.latest
        assert latest["episode"].seq == 1 and tagged_episode(latest["obstacles"]) == 1
        assert latest["goal"].header.stamp == latest["episode"].stamp
        b = env.unwrapped.b
        assert np.array_equal(obs, b.observation({**first, **new, "episode": episode_header(1, 1.5)}))
        stale = b.observation({**first, **drone_episode(None, (2.0, -1.0, 1.2), 1.0)})  # no number heard
        assert not np.array_equal(obs, stale)
    finally:
        if env is not None:
            env.close()
        close(*services, commands, *pubs.values())


@needs_ros
def test_policy_node_faults_stop_the_robot(ros, cartpole_export, goto_export, tmp_path):
    from jaxrobo_ros.system import rospy as get

    rospy = get()
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64

    commands = Listener("/cartpole_v0/foot_joint_velocity_controller/command", Float64)
    sim = ros.node("sim", cartpole_export, "--speed", "1", name="fault_sim")
    policy = ros.node("policy", cartpole_export, name="fault_policy")
    try:
        # the sim killed mid-episode: the policy node stops the cart and says why
        assert commands.wait(25, timeout=90), log(policy)
        os.killpg(sim.pid, signal.SIGKILL)
        sim.wait()
        assert eventually(lambda: "stopping the robot (zero command): no new /cartpole_v0/joint_states"
                          in log(policy), timeout=30), log(policy)
        before = len(commands.got)  # the watchdog's commands from here on: zero
        assert commands.wait(before + 1, timeout=5) and commands.got[-1].data == 0.0
        # the node acts again on fresh readings (here from this test), then a NaN stops it at once
        pub = rospy.Publisher("/cartpole_v0/joint_states", JointState, queue_size=10)
        assert subscribed_by(pub, "/jaxrobo_policy"), log(policy)

        def joints(t, pole=0.01):
            m = JointState(name=["foot_joint", "pole_joint"], position=[0.0, pole], velocity=[0.0, 0.0])
            m.header.stamp = rospy.Time.from_sec(t)
            return m

        before = len(commands.got)
        for k in range(5):
            pub.publish(joints(1000.0 + 0.04 * k))
            time.sleep(0.05)
        assert commands.wait(before + 5, timeout=5)
        assert eventually(lambda: "acting again" in log(policy), timeout=10), log(policy)
        before = len(commands.got)
        pub.publish(joints(1000.2, pole=float("nan")))
        assert commands.wait(before + 1, timeout=5)
        assert commands.got[-1].data == 0.0
        assert eventually(lambda: "/cartpole_v0/joint_states: non-finite value in the message" in log(policy),
                          timeout=10), log(policy)
        # a sensor that stops: (nothing more is published) the watchdog keeps the cart stopped
        before = len(commands.got)
        assert commands.wait(before + 1, timeout=5)
        assert all(m.data == 0.0 for m in commands.got[before:])
        assert policy.poll() is None  # still running
        policy.send_signal(signal.SIGINT)
        assert policy.wait(timeout=30) == 0
    finally:
        close(sim, policy, commands)
    assert "Traceback" not in log(policy)

    # an export written before exports carried the robot section, the robot section of another task, topics of
    # another task: one line, exit 2, nothing started
    meta = json.loads((Path(cartpole_export) / "policy.json").read_text())
    drone = json.loads((Path(goto_export) / "policy.json").read_text())["robot"]
    drone_topics = os.path.join(ROOT, "jaxrobo_ros", "topics", "quadcopter.yaml")
    old, other = tmp_path / "old", tmp_path / "other"
    for where, robot in ((old, None), (other, drone)):
        shutil.copytree(cartpole_export, where)
        (where / "policy.json").write_text(json.dumps({**{k: v for k, v in meta.items() if k != "robot"},
                                                       **({"robot": robot} if robot else {})}))
    for args, says in (((str(old),), (f"{old}: policy.json has no robot section", "export it again (jaxrobo "
                                      f"export RUN --out {old} --overwrite)")),
                       ((str(other),), ("robot: a quadcopter with 5 actions does not take the actions of a tabular "
                                        "policy",)),
                       ((cartpole_export, "--topics", drone_topics), ("family='quadcopter', but the policy's task "
                                                                      "is a cartpole",))):
        p = ros.node("policy", *args, name="refused")
        assert p.wait(timeout=BOUND) == 2
        text = log(p)
        assert all(x in text for x in says) and "Traceback" not in text and text.count("\n") == 1, text


@needs_ros
def test_drone_node_builds_the_training_observation_from_messages(ros, goto_export, tmp_path):
    """Readings sent by hand, the goal as a parameter: each command is the runner's action on the observation the
    native port builds from the same readings (the obstacles map is empty: nothing publishes it)."""
    import yaml
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Range

    from jaxrobo.interop.numpy_policy import Policy
    from jaxrobo_ros.system import rospy as get
    from jaxrobo.ros.bridge import make_bridge, make_env
    from jaxrobo_ros.bridge import HERE, SONARS

    rospy = get()
    cfg = yaml.safe_load(open(os.path.join(HERE, "topics", "quadcopter.yaml")))
    cfg["goal_param"] = "/jaxrobo_test/goal"
    topics = tmp_path / "topics.yaml"
    topics.write_text(yaml.safe_dump(cfg))
    goal = np.array([2.0, -1.0, 1.2])
    rospy.set_param("/jaxrobo_test/goal", goal.tolist())
    runner = Policy.load(goto_export)
    port = make_bridge(make_env(runner.meta)).port
    empty = {"kind": np.zeros(0, np.int32), "center": np.zeros((0, 3)), "size": np.zeros((0, 3)),
             "active": np.zeros(0, bool)}
    commands = Listener("/cmd_vel", Twist)
    pubs = {k: rospy.Publisher(cfg["topics"][k], Odometry if k == "odom" else Range, queue_size=10)
            for k in ("odom", *SONARS)}
    policy = ros.node("policy", goto_export, "--topics", str(topics), name="goal_param_policy")
    try:
        # this test's readings reach the node, and the node's commands this listener (not another node's)
        assert commands.connected_to(node_uri(policy, "/jaxrobo_policy")), log(policy)
        assert all(subscribed_by(p, "/jaxrobo_policy") for p in pubs.values()), log(policy)
        rng = np.random.default_rng(0)
        for k in range(6):
            t = rospy.Time.from_sec(10.0 + 0.3 * k)
            pos, yaw, vz = rng.uniform([-2, -2, 0.5], [2, 2, 1.5]), rng.uniform(-np.pi, np.pi), rng.uniform(-0.5, 0.5)
            sonars = rng.uniform(0.2, 4.0, 4)
            for name, value in zip(SONARS, sonars):
                m = Range(range=float(value))
                m.header.stamp = t
                pubs[name].publish(m)
            o = Odometry()
            o.header.stamp = t
            o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z = pos
            o.pose.pose.orientation.w, o.pose.pose.orientation.z = np.cos(yaw / 2), np.sin(yaw / 2)
            o.twist.twist.linear.z = vz
            pubs["odom"].publish(o)
            # the policy's commands: each action's Twist moves; a zero one is the watchdog's hold, which a machine
            # slow enough to leave the node a second without readings between two of these sends
            acted = lambda: [c for c in commands.got  # noqa: E731
                             if any((c.linear.x, c.linear.y, c.linear.z, c.angular.z))]
            end = time.monotonic() + 10
            while len(acted()) < k + 1 and time.monotonic() < end:
                commands.wait(len(commands.got) + 1, timeout=0.1)
            assert len(acted()) == k + 1, log(policy)
            quat = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
            obs = port.observation(pos, quat, vz, np.asarray(sonars, np.float32).astype(np.float64), goal, empty)
            want = port.command(runner(obs))[1]
            c = acted()[k]
            assert np.allclose([c.linear.x, c.linear.y, c.linear.z, c.angular.z], want), (k, c, want)
    finally:
        close(policy, commands, *pubs.values())
    assert "Traceback" not in log(policy)


@needs_ros
def test_policy_node_stops_when_the_master_restarts(ros, cartpole_export):
    from jaxrobo.ros.launch import start_master

    port = free_port()
    env = dict(ros.env, ROS_MASTER_URI=f"http://127.0.0.1:{port}")  # a master of its own, to restart
    master = start_master(port, env)
    sim = ros.node("sim", cartpole_export, "--speed", "1", name="restart_sim", env=env)
    policy = ros.node("policy", cartpole_export, name="restart_policy", env=env)
    try:
        assert eventually(lambda: "1 x real time" in log(sim), every=0.2), log(sim)
        time.sleep(2.0)
        assert policy.poll() is None, log(policy)
        close(master)
        master = start_master(port, env)
        assert policy.wait(timeout=60) == 3, log(policy)
    finally:
        close(sim, policy, master)
    text = log(policy)
    assert "stopped the robot (zero command): the ROS master at" in text and "was restarted" in text, text
    assert "Traceback" not in text, text


@needs_ros
def test_up_starts_master_sim_and_policy_and_stops_them(ros, cartpole_export):
    port = free_port()
    env = dict(ros.env, ROS_MASTER_URI=f"http://127.0.0.1:{port}")
    up = subprocess.run([sys.executable, "-m", "jaxrobo.cli", "ros", "up", cartpole_export, "--episodes", "2",
                         "--lockstep", "--port", str(port)], env=env, capture_output=True, text=True, timeout=BOUND,
                        cwd=ROOT)
    out = up.stdout + up.stderr
    assert up.returncode == 0, out
    assert "jaxrobo ros sim: 2 episodes" in out and "jaxrobo ros policy: CartPoleStayUp-v0" in out, out
    assert "Traceback" not in out, out
    from jaxrobo.ros.launch import master_up

    assert not master_up(env["ROS_MASTER_URI"])  # the master it started is gone


@needs_ros
@pytest.mark.skipif(shutil.which("roslaunch") is None, reason="roslaunch is not on PATH: apt-get install "
                    "python3-roslaunch (docs/ros.md)")
def test_roslaunch_file_starts_sim_and_policy(ros, cartpole_export):
    """The shipped launch file, by its path, on the fixture's master: the sim's episodes are flown by the policy's
    commands (one per state, as in-process), then the sim ends the launch."""
    from std_msgs.msg import Float64

    import jaxrobo_ros

    package = os.path.dirname(jaxrobo_ros.__file__)
    commands = Listener("/cartpole_v0/foot_joint_velocity_controller/command", Float64)
    env = dict(ros.env, ROS_PACKAGE_PATH=package, JAXROBO_PYTHON=sys.executable)
    port = ros.env["ROS_MASTER_URI"].rsplit(":", 1)[1]
    try:
        r = subprocess.run(["roslaunch", "-p", port, os.path.join(package, "jaxrobo.launch"),
                            f"export:={cartpole_export}", "episodes:=2", "lockstep:=true", "seed:=4"], env=env,
                           capture_output=True, text=True, timeout=BOUND, cwd=ROOT)
    finally:
        close(commands)
    out = r.stdout + r.stderr
    steps = sum(e["length"] for e in in_process(cartpole_export, 2, 4))
    assert "jaxrobo ros sim: 2 episodes" in out and "jaxrobo ros policy: CartPoleStayUp-v0" in out, out
    assert f"jaxrobo ros policy: {steps} commands" in out, (steps, out)
    # lockstep: the sim stepped once per command it received, so its episodes' steps are the policy's commands
    assert f"mean steps {steps / 2:.1f}" in out, (steps, out)
    # an outside subscriber sees the commands on the topic; the first few may go out before rospy has connected it
    # (CI once saw 41 of 44) and the policy's zero command on stopping may follow, so only their arrival is asserted
    # here: their count is the sim's, above
    assert commands.got, (len(commands.got), steps)
    assert "Traceback" not in out, out


@needs_ros
@pytest.mark.skipif(shutil.which("roslaunch") is None, reason="roslaunch is not on PATH: apt-get install "
                    "python3-roslaunch (docs/ros.md)")
def test_roslaunch_remappings_and_names_reach_the_nodes(ros, cartpole_export, tmp_path):
    """A user's launch file starting the package's nodes under its own names with the cart-pole's topics remapped
    (as for Gazebo or a robot whose topics differ): the nodes take roslaunch's ``__name:=`` and ``from:=to``
    arguments, and the policy flies the lockstep sim's episodes over the remapped topics alone."""
    from std_msgs.msg import Float64

    import jaxrobo_ros

    package = os.path.dirname(jaxrobo_ros.__file__)
    command, joints = "/cartpole_v0/foot_joint_velocity_controller/command", "/cartpole_v0/joint_states"
    launch = tmp_path / "robot.launch"
    launch.write_text(f"""<launch>
  <remap from="{command}" to="/robot/cart_cmd"/>
  <remap from="{joints}" to="/robot/joints"/>
  <node name="cart_sim" pkg="jaxrobo_ros" type="jaxrobo_ros" output="screen" required="true"
        args="sim {cartpole_export} --episodes 2 --lockstep --seed 4"/>
  <node name="cart_policy" pkg="jaxrobo_ros" type="jaxrobo_ros" output="screen" args="policy {cartpole_export}"/>
</launch>
""")
    remapped, original = Listener("/robot/cart_cmd", Float64), Listener(command, Float64)
    env = dict(ros.env, ROS_PACKAGE_PATH=package, JAXROBO_PYTHON=sys.executable)
    port = ros.env["ROS_MASTER_URI"].rsplit(":", 1)[1]
    try:
        r = subprocess.run(["roslaunch", "-p", port, str(launch)], env=env, capture_output=True, text=True,
                           timeout=BOUND, cwd=ROOT)
    finally:
        close(remapped, original)
    out = r.stdout + r.stderr
    steps = sum(e["length"] for e in in_process(cartpole_export, 2, 4))
    assert "jaxrobo ros sim: 2 episodes" in out, out
    assert "in native MuJoCo as /cart_sim" in out and "as /cart_policy every" in out, out
    assert "on /robot/cart_cmd" in out, out
    # lockstep: the sim stepped once per command it received on /robot/cart_cmd, and took its episodes' states to
    # the policy on /robot/joints
    assert f"jaxrobo ros policy: {steps} commands" in out, (steps, out)
    assert remapped.got and not original.got, (len(remapped.got), len(original.got))
    assert "Traceback" not in out, out


QLEARN = os.path.join(ROOT, "examples", "ros", "cartpole_qlearn.py")


@pytest.mark.slow
@needs_ros
def test_seed_style_qlearning_against_the_sim_sees_the_local_episodes(ros):
    """Through the topics and Gazebo's services, the seed's loop trains on exactly the episodes of the sim's model in
    its own process: every episode length the same (the learner's choices follow the observations, so one
    observation off by a bit, a lost reset or a command that stepped the wrong state would change them)."""
    sim = ros.node("sim", "CartPoleStayUp-v0", "--lockstep", "--seed", "3", name="ql_sim")
    over_ros, local = ros.tmp / "ql.json", ros.tmp / "ql_local.json"
    args = ("--episodes", "60", "--seed", "5")
    try:
        r = ros.script(QLEARN, *args, "--out", str(over_ros))
        assert r.returncode == 0, r.stdout + r.stderr
    finally:
        close(sim)
    r = ros.script(QLEARN, *args, "--local", "--sim-seed", "3", "--out", str(local))
    assert r.returncode == 0, r.stdout + r.stderr
    lengths = json.loads(over_ros.read_text())
    assert len(lengths) == 60 and lengths == json.loads(local.read_text())


@pytest.mark.slow
def test_seed_style_qlearning_improves_on_average(tmp_path):
    """The seed's learner, as the example runs it. One run may never leave its first policy (9 of 40 seeds gained
    under 10 steps in 200 episodes on this machine, and which seeds do depends on the CPU's last bits: CI's run of
    seed 0 did not learn where this machine's did), so the claim is on the mean gain of 16 seeds, the last 50
    episodes over the first 25. Over 40 seeds: mean 65 steps, standard deviation 57, so a 16-seed mean has a
    standard error of 14; every run of 16 consecutive seeds gave 42-91. The bound, 15, sits 3.5 errors below."""
    import runpy

    main = runpy.run_path(QLEARN)["main"]
    gains = []
    for seed in range(16):
        out = tmp_path / f"{seed}.json"
        assert main(["--local", "--episodes", "200", "--seed", str(seed), "--out", str(out)]) == 0
        lengths = np.array(json.loads(out.read_text()))
        gains.append(lengths[-50:].mean() - lengths[:25].mean())
    assert np.mean(gains) > 15, np.round(gains, 1)


def test_without_ros_the_command_says_how_to_install(monkeypatch, capsys):
    from jaxrobo.cli import main
    from jaxrobo_ros import policy_node, system

    monkeypatch.setattr(system, "unavailable_reason", lambda: system.INSTALL)
    for run, args in ((main, ["ros", "policy", "somewhere"]), (main, ["ros", "sim", "CartPoleStayUp-v0"]),
                      (main, ["ros", "up", "somewhere"]), (policy_node.main, ["somewhere"])):
        assert run(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "apt-get install ros-core python3-rospy" in err, err


@pytest.mark.parametrize("edit,says", [
    (lambda c: c["topics"].__setitem__("odom", "drone/odom"), "topics.odom must be a global topic name"),
    (lambda c: c["topics"].pop("sonar_down"), "topics.sonar_down must be a global topic name"),
    (lambda c: c.__setitem__("stale_after", -1), "stale_after=-1: must be null or a number of seconds in (0, 60]"),
    (lambda c: c.__setitem__("max_age", "soon"), "max_age='soon'"),
    (lambda c: c.__setitem__("family", "cartpole"), "family='cartpole', but the policy's task is a quadcopter"),
    (lambda c: c.__setitem__("goal_param", 3), "goal_param must be null or a parameter name"),
])
def test_topic_files_are_checked_field_by_field(tmp_path, edit, says):
    import yaml

    from jaxrobo_ros.bridge import HERE, load_topics
    from jaxrobo_ros.system import SetupError

    cfg = yaml.safe_load(open(os.path.join(HERE, "topics", "quadcopter.yaml")))
    assert load_topics("quadcopter")["topics"]["cmd_vel"] == "/cmd_vel"
    edit(cfg)
    path = tmp_path / "topics.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with pytest.raises(SetupError) as err:
        load_topics("quadcopter", str(path))
    assert says in str(err.value) and str(path) in str(err.value)
    path.write_text("[not, a, mapping")
    with pytest.raises(SetupError, match="cannot be read as YAML"):
        load_topics("quadcopter", str(path))


@pytest.mark.parametrize("edit,says", [
    (lambda r: r.__setitem__("family", "arm"), "robot: family='arm': expected one of quadcopter, cartpole"),
    (lambda r: r.__setitem__("period", -1), "robot: period=-1: expected a number in [1e-06, 60.0]"),
    (lambda r: r.__setitem__("steps", [0.1, None, 0.2, 0.3]), "robot: steps: expected finite numbers of shape [n]"),
    (lambda r: r.pop("vmax"), "robot: no field 'vmax'"),
    (lambda r: r.__setitem__("round_obs", "no"), "robot: round_obs='no': expected true or false"),
    (lambda r: r.__setitem__("steps", [0.1, -0.1]), "robot: a cartpole with 2 actions does not take the actions"),
])
def test_robot_sections_are_checked_field_by_field(cartpole_export, tmp_path, edit, says):
    """policy.json's robot section is read back as hostile: the node refuses it in one line naming the field."""
    from jaxrobo_ros.policy_node import load_export
    from jaxrobo_ros.system import SetupError

    bad = tmp_path / "bad"
    shutil.copytree(cartpole_export, bad)
    meta = json.loads((bad / "policy.json").read_text())
    edit(meta["robot"])
    (bad / "policy.json").write_text(json.dumps(meta))
    with pytest.raises(SetupError) as err:
        load_export(str(bad))
    assert says in str(err.value) and str(bad / "policy.json") in str(err.value), str(err.value)


def test_a_nodes_log_lines_reach_a_file_as_they_are_written(tmp_path):
    """rospy writes INFO lines to stdout without a flush: a node's stdout, redirected to a file, is line-buffered
    (jaxrobo_ros.system.line_buffered), so "acting again" shows while the node runs, not at its exit."""
    code = ("import sys, time; from jaxrobo_ros.system import line_buffered; line_buffered(); "
            "sys.stdout.write('acting again\\n'); time.sleep(30)")
    log_path = tmp_path / "node.log"
    with open(log_path, "w") as out:
        p = subprocess.Popen([sys.executable, "-c", code], stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                             env={**os.environ, "PYTHONUNBUFFERED": ""})
    try:
        assert eventually(lambda: "acting again" in log_path.read_text(), timeout=20)
    finally:
        p.kill()
        p.wait()


def test_a_stop_signal_is_heard_while_the_main_thread_holds_a_lock():
    """The nodes' SIGINT/SIGTERM handler (stop_on_signals) takes no lock: Python runs a handler in the main thread
    between bytecodes, where that thread may hold one (an Event's own, inside Event.wait). Raised while the main
    thread holds an Event's lock, the signal is recorded and the process goes on; a handler that set an Event hung
    there (the node was killed without stopping the robot or writing its stats). No rospy needed."""
    script = """if True:
        import os, signal, threading
        from jaxrobo_ros.system import stop_on_signals
        stopping = stop_on_signals()
        event = threading.Event()
        def call():
            return 1
        with event._cond:  # what Event.wait holds for a few bytecodes
            os.kill(os.getpid(), signal.SIGINT)
            call()  # the pending handler runs here, inside the lock
        print("stopping", stopping == [signal.SIGINT])
    """
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")]))}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0 and r.stdout.strip() == "stopping True", r.stdout + r.stderr
