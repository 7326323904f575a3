"""The middleware settings every process of the project starts DDS with, unless the user set
them: free of rclpy, so they apply before a participant exists, in the nodes (through
``ros/executor.py``), the launcher's and the benchmark's helper nodes, and the `ros2 launch`
process itself (the launch file), whose children inherit them.

- ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``: DDS stays on this machine.
- ``FASTRTPS_DEFAULT_PROFILES_FILE``: Fast DDS's discovery timing and readers' memory that is
  freed once a message is taken (``config/fastdds.xml`` says why), with
  ``RMW_FASTRTPS_USE_QOS_FROM_XML=1``, without which rmw_fastrtps ignores the file's memory
  policies; a user's own profile file wins, and then neither is set.
"""
from __future__ import annotations

import os

from exit_decision.config import ConfigError, default_config_dir


def apply_dds_defaults() -> None:
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if {'FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'} & set(os.environ):
        return
    try:
        profile = default_config_dir() / 'fastdds.xml'
    except ConfigError:
        return   # not installed: the node says so when it loads its config
    if profile.is_file():
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile)
        os.environ.setdefault('RMW_FASTRTPS_USE_QOS_FROM_XML', '1')
