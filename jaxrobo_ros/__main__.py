"""``python -m jaxrobo_ros``: prints this directory, the ROS package ``jaxrobo_ros``, for ``ROS_PACKAGE_PATH``."""
import os
import sys

if sys.argv[1:]:
    print("usage: python -m jaxrobo_ros  (prints the ROS package's directory for ROS_PACKAGE_PATH)", file=sys.stderr)
    sys.exit(2)
print(os.path.dirname(os.path.abspath(__file__)))
