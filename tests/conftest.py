"""Test-wide set-up: every test run gets a private ROS graph.

A domain id derived from the process id (unless ROS_DOMAIN_ID is already set) plus localhost-only
discovery keep concurrent test runs and any other ROS 2 processes on the machine apart. Set before rclpy
is imported anywhere; subprocesses inherit it.
"""

import os

os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")

# Imported only now: rclpy must see the environment above.
from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402
from node_procs import Processes, RosPeer  # noqa: E402

# Fuzz tests (marked `fuzz`) draw few examples in `make test` and many in `make fuzz`
# (HYPOTHESIS_PROFILE=fuzz); neither has a deadline, as timings on a loaded CI machine vary.
settings.register_profile("default", max_examples=40, deadline=None)
settings.register_profile(
    "fuzz", max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


DDS_FIXTURES = frozenset({"procs", "peer"})
"""Fixtures that start nodes or an rclpy peer: a test that uses one is marked `dds` without saying so."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if DDS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.dds)


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Processes]:
    """Node processes of one test, logging into its tmp_path; killed at the end."""
    processes = Processes(tmp_path)
    yield processes
    processes.close()


@pytest.fixture
def peer() -> Iterator[RosPeer]:
    """An rclpy node of the test process to publish, subscribe and call services with."""
    ros = RosPeer("playseg_test_peer")
    yield ros
    ros.close()
