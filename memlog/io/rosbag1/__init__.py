"""ROS 1 bag reading (v2.0 bags, via rosbags; a record scanner for damaged indexes)."""

from memlog.errors import LogReadError
from memlog.io.rosbag1.reader import Ros1BagLog

__all__ = ["Ros1BagLog", "LogReadError"]
