"""``jaxrobo ros up EXPORT_DIR``: a master on localhost (``roscore -p PORT``, unless one answers there), the sim node
of the export's task and the policy node, as child processes; Ctrl-C (or the sim finishing its ``--episodes``)
stops them all: what ``roslaunch jaxrobo_ros jaxrobo.launch`` does (the ROS package :mod:`jaxrobo_ros`), without
roslaunch. The policy node runs as ``python -m jaxrobo_ros.policy_node`` (without JAX), as on a robot."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

def master_up(uri: str) -> bool:
    from jaxrobo_ros.system import rospy

    rospy()
    import rosgraph

    return rosgraph.is_master_online(uri)


def ros_env(port: int) -> dict:
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}")
    env.setdefault("ROS_HOSTNAME", "127.0.0.1")
    return env


def start_master(port: int, env: dict, timeout: float = 20.0) -> subprocess.Popen | None:
    """A ``roscore`` on ``port`` (None if a master already answers there), once it answers."""
    uri = env["ROS_MASTER_URI"]
    if master_up(uri):
        return None
    proc = subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if master_up(uri):
            return proc
        if proc.poll() is not None:
            break
        time.sleep(0.1)
    stop([proc])
    raise RuntimeError(f"roscore -p {port} did not answer at {uri} within {timeout:g} s")


def stop(procs) -> None:
    """SIGINT, then SIGKILL after 5 s, to each process group started here."""
    for p in procs:
        if p is not None and p.poll() is None:
            os.killpg(p.pid, signal.SIGINT)
    for p in procs:
        if p is None:
            continue
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def up(args) -> int:
    env = ros_env(args.port)
    try:
        master = start_master(args.port, env)
    except RuntimeError as err:
        print(f"jaxrobo ros up: {err}", file=sys.stderr)
        return 2
    me = [sys.executable, "-m", "jaxrobo.cli", "ros"]
    sim = me + ["sim", args.export_dir, "--episodes", str(args.episodes), "--seed", str(args.seed), "--speed",
                str(args.speed)] + (["--lockstep"] if args.lockstep else [])
    procs = [subprocess.Popen(sim, env=env, start_new_session=True),
             subprocess.Popen([sys.executable, "-m", "jaxrobo_ros.policy_node", args.export_dir], env=env,
                              start_new_session=True)]
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt))
    rc = 0
    try:
        while all(p.poll() is None for p in procs):
            time.sleep(0.2)
        rc = next(p.returncode for p in procs if p.poll() is not None)
    except KeyboardInterrupt:
        pass
    finally:
        stop(procs + [master])
    return rc

