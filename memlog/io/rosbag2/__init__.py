"""ROS 2 bag reading (sqlite3 and mcap storage, via rosbags; a row reader for damaged databases)."""

from memlog.errors import LogReadError
from memlog.io.rosbag2.reader import Ros2BagLog

__all__ = ["Ros2BagLog", "LogReadError"]
