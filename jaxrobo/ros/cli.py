"""``jaxrobo ros policy|sim|up``: the ROS 1 nodes (docs/ros.md). Without rospy: one line saying how to install it,
exit 2."""
from __future__ import annotations

import argparse
import sys


def configure_parser(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="ros_command", metavar="{policy,sim,up}")
    sub.required = True
    from jaxrobo_ros import policy_node

    policy_node.configure_parser(sub.add_parser(
        "policy", help="an exported policy as a rospy node on the task's topics (no JAX: python -m "
        "jaxrobo_ros.policy_node runs the same node without jaxrobo's command line)"))
    s = sub.add_parser("sim", help="the task's robot in native MuJoCo behind the seed's topics and /gazebo services")
    s.add_argument("env_id", metavar="ID", help="a task id with a native port (QuadcopterGoto-v2, CartPoleStayUp-v0, "
                   "...) or an export directory (its task as the run configured it)")
    s.add_argument("--episodes", type=int, default=0,
                   help="run this many episodes back to back, then exit (0: episodes change on /gazebo/reset_*)")
    s.add_argument("--seed", type=int, default=12345, help="key of the episodes' resets")
    s.add_argument("--lockstep", action="store_true",
                   help="one control period per state, on the one command that answers it (deterministic)")
    s.add_argument("--speed", type=float, default=1.0, help="x real time without --lockstep; 0: as fast as possible")
    s.add_argument("--topics", default=None, help="topic YAML (default: jaxrobo_ros/topics/<family>.yaml)")
    s.add_argument("--results", default=None, help="write each episode's steps and success here (JSON)")
    s.set_defaults(ros_args=[])  # ROS's own name:=value arguments, as for the policy (jaxrobo.cli.main)
    u = sub.add_parser("up", help="master, sim and policy in one command (the sim's task: the export's)")
    u.add_argument("export_dir", metavar="EXPORT_DIR")
    u.add_argument("--episodes", type=int, default=0)
    u.add_argument("--seed", type=int, default=12345)
    u.add_argument("--lockstep", action="store_true")
    u.add_argument("--speed", type=float, default=1.0)
    u.add_argument("--port", type=int, default=11311, help="the master's port (localhost)")
    u.set_defaults(ros_args=[])


def run(args: argparse.Namespace) -> int:
    from jaxrobo_ros.system import unavailable_reason

    why = unavailable_reason()
    if why is not None:
        print(f"jaxrobo ros: {why}", file=sys.stderr)
        return 2
    if args.ros_command == "up" and args.ros_args:
        print(f"jaxrobo ros up: {' '.join(args.ros_args)}: name:=value arguments are a node's (jaxrobo ros policy, "
              "jaxrobo ros sim, or the nodes of jaxrobo.launch)", file=sys.stderr)
        return 2
    if args.ros_command == "sim" and (args.episodes < 0 or args.speed < 0):
        print("jaxrobo ros sim: --episodes and --speed must be >= 0", file=sys.stderr)
        return 2
    from jaxrobo.core.config import ConfigError
    from jaxrobo_ros.system import SetupError

    try:
        if args.ros_command == "policy":
            from jaxrobo_ros import policy_node

            return policy_node.run(args)
        if args.ros_command == "sim":
            from jaxrobo.ros import sim_node

            return sim_node.run(args)
        from jaxrobo.ros import launch

        return launch.up(args)
    except (ConfigError, SetupError) as err:
        print(f"jaxrobo ros {args.ros_command}: {err}", file=sys.stderr)
        return 2
