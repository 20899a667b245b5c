"""Two hosts over DDS: the live graph split across two network namespaces made by the test, joined by a
virtual Ethernet link, as a robot and a server on one network are. Robot side: bag_player + topic_adapter
(`playseg up robot.yaml`); server side: segmenter + recorder (`playseg up server.yaml`). Discovery as
across real hosts: the same ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET and each side's peer in
ROS_STATIC_PEERS; DDS over UDP only (no shared memory between the "hosts"). The recorded PlaySteps and
segments equal `playseg convert --segment` of the bag: nothing is lost on the way.

Needs root with CAP_SYS_ADMIN and CAP_NET_ADMIN for `ip netns`, as the project's machines and CI have."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from node_procs import ROOT, node_env, wait_for_log
from test_demo_robot import _untrained_tabletop_model
from test_replay_up import assert_recorded_as_converted

from playseg_core.data.dataset import PlayDataset
from playseg_ros.cli import main

TABLETOP = ROOT / "bags" / "tabletop"
BAG = TABLETOP / "tabletop-1"
MAPPING = TABLETOP / "mapping.yaml"
LINK = "pslink0"
"""The veth's name at both ends (each end lives in its own namespace)."""


@dataclass(frozen=True)
class Host:
    namespace: str
    address: str


def ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True)
    assert done.returncode == 0, f"ip {' '.join(args)}: {done.stderr.strip()}"


@pytest.fixture
def hosts() -> Iterator[tuple[Host, Host]]:
    """Two network namespaces with one veth link between them (10.X.Y.1 and .2/24), multicast routed.
    The link is made inside the namespaces (nothing is left in the machine's own namespace), and every
    process still in them is killed before they go."""
    tag = os.getpid() % 100_000
    subnet = f"10.{200 + tag % 50}.{tag // 50 % 250}"
    robot, server = Host(f"psrobot{tag}", f"{subnet}.1"), Host(f"psserver{tag}", f"{subnet}.2")
    made: list[str] = []
    try:
        for host in (robot, server):
            subprocess.run(["ip", "netns", "del", host.namespace], capture_output=True)  # a killed run's
            ip("netns", "add", host.namespace)
            made.append(host.namespace)
        ip("link", "add", LINK, "netns", robot.namespace, "type", "veth",
           "peer", "name", LINK, "netns", server.namespace)  # fmt: skip
        for host in (robot, server):
            ip("-n", host.namespace, "addr", "add", f"{host.address}/24", "dev", LINK)
            ip("-n", host.namespace, "link", "set", LINK, "up", "multicast", "on")
            ip("-n", host.namespace, "link", "set", "lo", "up")
            ip("-n", host.namespace, "route", "add", "224.0.0.0/4", "dev", LINK)  # SPDP's multicast
        yield robot, server
    finally:
        for namespace in made:
            pids = subprocess.run(["ip", "netns", "pids", namespace], capture_output=True, text=True).stdout
            for pid in pids.split():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(pid), signal.SIGKILL)
            subprocess.run(["ip", "netns", "del", namespace], capture_output=True)


def received_bytes(host: Host) -> int:
    """Bytes the host's end of the link has received."""
    shown = subprocess.run(
        ["ip", "-n", host.namespace, "-s", "-j", "link", "show", "dev", LINK],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    return int(json.loads(shown.stdout)[0]["stats64"]["rx"]["bytes"])


def host_env(peer: Host) -> dict[str, str]:
    """A host's ROS environment as across machines: same domain, subnet discovery, the peer named."""
    return dict(
        node_env(),
        ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET",
        ROS_STATIC_PEERS=peer.address,
        FASTDDS_BUILTIN_TRANSPORTS="UDPv4",
    )


def graph(path: Path, nodes: list[dict]) -> Path:
    path.write_text(yaml.safe_dump({"ros_domain_id": int(os.environ["ROS_DOMAIN_ID"]), "nodes": nodes}))
    return path


@pytest.mark.dds
def test_a_graph_split_across_two_hosts_loses_nothing(hosts: tuple[Host, Host], tmp_path: Path) -> None:
    robot, server = hosts
    model = _untrained_tabletop_model(tmp_path / "tabletop.pt")
    quiet = ["--mapping", str(MAPPING), "--quiet"]
    assert main(["convert", str(BAG), "--out", str(tmp_path / "data"), *quiet, "--segment", str(model)]) == 0
    converted = PlayDataset.open(tmp_path / "data")
    episode, expected = converted.episode(0), converted.segments(0, truth=True)
    assert expected

    recorded = tmp_path / "recorded"
    robot_graph = graph(tmp_path / "robot.yaml", [
        {"name": "player", "node": "bag_player", "parameters": {"bag": str(BAG), "clock": True},
         "exit_ends_graph": True},
        # the steps' readers are on the other host, where this graph cannot count them: say how many
        {"name": "adapter", "node": "topic_adapter",
         "parameters": {"mapping": str(MAPPING), "episode_id": "tabletop-1", "use_sim_time": True,
                        "wait_for_subscribers": 2}},
    ])  # fmt: skip
    server_graph = graph(tmp_path / "server.yaml", [
        {"name": "segmenter", "node": "segmenter", "parameters": {"model": str(model)}},
        {"name": "recorder", "node": "recorder",
         "parameters": {"output": str(recorded), "topics": ["/play/steps", "/segments"]}},
    ])  # fmt: skip
    up = [sys.executable, "-m", "playseg_ros.cli", "up"]
    server_log, robot_log = tmp_path / "server.log", tmp_path / "robot.log"
    with open(server_log, "wb") as out:
        server_up = subprocess.Popen(
            ["ip", "netns", "exec", server.namespace, *up, str(server_graph)], cwd=ROOT,
            env=host_env(robot), stdout=out, stderr=subprocess.STDOUT,
        )  # fmt: skip
    try:
        with open(robot_log, "wb") as out:
            robot_up = subprocess.run(
                ["ip", "netns", "exec", robot.namespace, *up, str(robot_graph)], cwd=ROOT,
                env=host_env(server), stdout=out, stderr=subprocess.STDOUT, timeout=300,
            )  # fmt: skip
        assert robot_up.returncode == 0, robot_log.read_text()[-4000:]
        wait_for_log(server_log, r"episode 'tabletop-1:0' ended after \d+ steps", 60, server_up)
        server_up.send_signal(signal.SIGINT)
        assert server_up.wait(timeout=60) == 0, server_log.read_text()[-4000:]
    finally:
        if server_up.poll() is None:
            server_up.kill()
    # the steps crossed the link: the server received at least their frames' bytes over it
    frame_bytes = sum(frames.nbytes for frames in episode.images.values())
    assert received_bytes(server) > frame_bytes, (received_bytes(server), frame_bytes)
    for log in (robot_log, server_log):
        text = log.read_text()
        assert "Traceback" not in text and "gap at the start" not in text, text[-4000:]

    assert_recorded_as_converted(recorded, episode, expected)
