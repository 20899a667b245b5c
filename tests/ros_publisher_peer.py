"""Peer process for test_messages: publishes every sample message on /test_<Name> until killed."""

import sys

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

sys.path.insert(0, __import__("os").path.dirname(__file__))
from msg_samples import SAMPLES  # noqa: E402


def main() -> None:
    rclpy.init()
    node = rclpy.create_node("playseg_test_publisher")
    qos = QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
    )
    pubs = [
        (node.create_publisher(type(make()), f"/test_{name}", qos), make) for name, make in SAMPLES.items()
    ]

    def publish_all() -> None:
        for pub, make in pubs:
            pub.publish(make())

    node.create_timer(0.2, publish_all)
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
