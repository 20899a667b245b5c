"""rosbag2-compatible bags without a ROS graph: schema and metadata, writer, reader, recovery, info."""

from playseg_ros.bag.errors import BagError
from playseg_ros.bag.info import bag_info_text
from playseg_ros.bag.reader import BagReader, RawMessage
from playseg_ros.bag.recovery import RecoveredFile, recover_bag
from playseg_ros.bag.schema import BagSummary, QosProfile, TopicInfo, ros2msg_definition, topic_info
from playseg_ros.bag.writer import BagWriter, partial_path

__all__ = [
    "BagError",
    "BagReader",
    "BagSummary",
    "BagWriter",
    "QosProfile",
    "RawMessage",
    "RecoveredFile",
    "TopicInfo",
    "bag_info_text",
    "partial_path",
    "recover_bag",
    "ros2msg_definition",
    "topic_info",
]
