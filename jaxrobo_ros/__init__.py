"""jaxrobo's robot side for ROS 1: what runs on the robot's computer with numpy, yaml and rospy alone (no JAX, no
task module, no MuJoCo), from a directory written by ``jaxrobo export`` (docs/ros.md).

* :mod:`jaxrobo_ros.policy_node`: the exported policy as a rospy node (``python -m jaxrobo_ros.policy_node
  EXPORT_DIR``, or ``jaxrobo ros policy EXPORT_DIR`` where jaxrobo is installed);
* :mod:`jaxrobo_ros.bridge`: the topics (``topics/<family>.yaml``), the readings and the command messages;
* :mod:`jaxrobo_ros.system`: where rospy comes from (the system's packages).

This directory is also the ROS package ``jaxrobo_ros`` (``package.xml``, ``jaxrobo.launch`` and the node wrapper
``jaxrobo_ros``): on ``ROS_PACKAGE_PATH`` (``python -m jaxrobo_ros`` prints it), ``roslaunch jaxrobo_ros
jaxrobo.launch export:=DIR`` starts the sim and the policy. The sim node and the Gymnasium env over ROS need the
task itself and live in :mod:`jaxrobo.ros`.

Nothing here imports ``jaxrobo``: a robot's computer needs only the export, numpy and rospy (``tests/test_ros.py``
checks it).
"""
