"""`make demo`: the main job on the embedded default.

Today: a play episode travels as PlayStep messages from one ROS 2 process to another over DDS and is
checked on arrival. Later work replaces this with the full pipeline (train, segment live, record, retrain).
"""

from __future__ import annotations

import subprocess
import sys
import time

NUM_STEPS = 50


def _publisher() -> None:
    import rclpy
    from playseg_msgs.msg import PlayStep
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node("playseg_demo_source")
    qos = QoSProfile(
        depth=NUM_STEPS + 1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    pub = node.create_publisher(PlayStep, "/play/steps", qos)
    for step in range(NUM_STEPS + 1):
        msg = PlayStep(episode_id="demo-0", step=step, episode_end=step == NUM_STEPS)
        msg.observation.height = msg.observation.width = 64
        msg.observation.encoding = "rgb8"
        msg.observation.step = 64 * 3
        msg.observation.data = bytes([step % 256]) * (64 * 64 * 3)
        msg.action = [] if step == NUM_STEPS else [float(step % 3)]
        pub.publish(msg)
    end = time.monotonic() + 20
    try:
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.1)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass  # stopped by the demo: SIGTERM shuts rclpy down


def run_demo() -> int:
    import rclpy
    from playseg_msgs.msg import PlayStep
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    print("[demo] starting a PlayStep publisher in a second process ...")
    source = subprocess.Popen([sys.executable, "-c", "from playseg_ros.demo import _publisher; _publisher()"])
    rclpy.init()
    node = rclpy.create_node("playseg_demo_sink")
    steps: list[int] = []
    qos = QoSProfile(
        depth=NUM_STEPS + 1,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    node.create_subscription(PlayStep, "/play/steps", lambda m: steps.append(m.step), qos)
    deadline = time.monotonic() + 20
    while len(steps) < NUM_STEPS + 1 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    source.terminate()
    source.wait()
    rclpy.shutdown()
    ok = steps == list(range(NUM_STEPS + 1))
    print(f"[demo] received {len(steps)} of {NUM_STEPS + 1} PlayStep messages over DDS, in order: {ok}")
    return 0 if ok else 1
