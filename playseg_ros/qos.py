"""QoS per stream, chosen so that nothing is silently lost by default.

- Play steps and labelled segments: RELIABLE + KEEP_ALL history (volatile). A segment decoder must see
  every step in order, and the trainer must see every segment: a slow subscriber's KEEP_ALL reader queues
  the backlog instead of dropping (best effort would drop under load without a trace).
- Annotations: RELIABLE + TRANSIENT_LOCAL (depth 1000), so a late-joining segmenter/trainer still gets
  the labels published before it started.
- Trainer status: RELIABLE + TRANSIENT_LOCAL depth 1: a late subscriber sees the latest status at once.
- Recorder: KEEP_ALL with RELIABLE by default. A reliable subscription does not match a best-effort
  publisher (e.g. a camera driver), so `reliability` is a recorder parameter.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

PLAY_STEPS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
SEGMENTS = PLAY_STEPS
ANNOTATIONS = QoSProfile(
    depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)
STATUS = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)


def recorder_qos(reliability: str) -> QoSProfile:
    """KEEP_ALL subscription with the configured reliability ('reliable' or 'best_effort')."""
    policy = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}[
        reliability
    ]
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=policy)
