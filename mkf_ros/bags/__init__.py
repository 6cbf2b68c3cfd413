"""Bags without rosbag2_py: read ROS 2 (MCAP, sqlite3) and ROS 1 bags, write Jazzy (v9) bags
atomically, fast NumPy codecs for the IMU messages, and synthetic bags with ground truth.

No rclpy here: everything works in a plain Python environment with rosbags installed.
"""

from mkf_ros.bags.reader import BagError, BagReader, Batch, TopicInfo, normalize_topic
from mkf_ros.bags.writer import STORAGES, BagWriter

__all__ = ["STORAGES", "BagError", "BagReader", "BagWriter", "Batch", "TopicInfo",
           "normalize_topic"]
