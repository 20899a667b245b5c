"""`playseg up CONFIG.yaml`: bring up a graph of playseg nodes, one OS process each (there is no
`ros2 launch` in the package registry).

Config::

    ros_domain_id: 77              # optional; default: the environment's
    nodes:
      - name: segmenter            # ROS node name (unique)
        node: segmenter            # recorder | segmenter | trainer | play_source | bag_player
        parameters: {model: build/demo/ps.pt}
        exit_ends_graph: false     # true: when this node exits, stop the whole graph

Each stream source waits for the subscribers the graph will have, unless the config sets its wait
(playseg_ros/wiring.py). Ctrl-C (SIGINT), SIGTERM or a graph-ending node stops the nodes upstream first,
each with SIGINT once the nodes publishing to it have exited (it hands on what it still holds and closes
its files); a node still running `shutdown_timeout_s` after its SIGINT is terminated, then killed.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from playseg_core.errors import PlaysegError
from playseg_core.yaml_io import load_yaml
from playseg_ros.wiring import GraphSpec, NodeSpec, stop_order, wire_waits

NODE_KINDS: dict[str, str] = {
    "recorder": "playseg_ros.nodes.recorder",
    "segmenter": "playseg_ros.nodes.segmenter",
    "trainer": "playseg_ros.nodes.trainer",
    "bag_player": "playseg_ros.nodes.bag_player",
    "topic_adapter": "playseg_ros.nodes.topic_adapter",  # a robot's standard topics -> PlaySteps
    "play_source": "playseg_ros.babyai.play_source",  # a domain's node: its bot's play
}
"""Node kind in a graph config -> the module whose ``main`` runs it."""

NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
"""What rcl accepts as a node name (a remapped `__node`)."""


def load_graph(path: str | Path) -> GraphSpec:
    """Parse and validate a graph config; errors name the file and the offending entry."""
    path = Path(path)
    raw = load_yaml(path, "graph config")  # YamlFileError (a ValueError) naming the file and entry
    if not isinstance(raw, dict) or not isinstance(raw.get("nodes"), list) or not raw["nodes"]:
        raise PlaysegError(f"{path}: expected a mapping with a non-empty 'nodes' list")
    nodes, names = [], set()
    for i, entry in enumerate(raw["nodes"]):
        where = f"{path}: nodes[{i}]"
        if not isinstance(entry, dict) or "name" not in entry or "node" not in entry:
            raise PlaysegError(f"{where}: each node needs 'name' and 'node'")
        if entry["node"] not in NODE_KINDS:
            raise PlaysegError(f"{where}: unknown node {entry['node']!r} (one of {', '.join(NODE_KINDS)})")
        if not isinstance(entry["name"], str) or not NODE_NAME.fullmatch(entry["name"]):
            raise PlaysegError(f"{where}: name {entry['name']!r}: a ROS node name is letters, digits and '_'")
        if entry["name"] in names:
            raise PlaysegError(f"{where}: duplicate node name {entry['name']!r}")
        if not isinstance(entry.get("parameters") or {}, dict):
            raise PlaysegError(f"{where}: parameters must be a mapping of parameter name to value")
        unknown = set(entry) - {"name", "node", "parameters", "exit_ends_graph"}
        if unknown:
            raise PlaysegError(f"{where}: unknown keys {sorted(unknown)}")
        names.add(entry["name"])
        nodes.append(
            NodeSpec(
                entry["name"],
                entry["node"],
                dict(entry.get("parameters") or {}),
                bool(entry.get("exit_ends_graph")),
            )
        )
    domain_id = raw.get("ros_domain_id")
    if domain_id is not None and (
        isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0
    ):
        raise PlaysegError(f"{path}: ros_domain_id {domain_id!r}: expected a non-negative integer")
    timeout = raw.get("shutdown_timeout_s", 15.0)
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not 0 < timeout < float("inf"):
        raise PlaysegError(f"{path}: shutdown_timeout_s {timeout!r}: expected a positive number of seconds")
    graph = GraphSpec(nodes, domain_id, float(timeout))
    graph.wired = wire_waits(graph)  # each stream waits for the subscribers this graph will have
    return graph


class _ParamsDumper(yaml.SafeDumper):
    """Writes a value used twice (one list for two parameters) twice: the ROS 2 parameter file parser
    refuses YAML aliases."""

    def ignore_aliases(self, data: object) -> bool:
        return True


def node_command(spec: NodeSpec, params_dir: Path) -> list[str]:
    """The command line that runs one node with its parameters (a ROS parameter file)."""
    params_file = params_dir / f"{spec.name}.yaml"
    params_file.write_text(yaml.dump({spec.name: {"ros__parameters": spec.parameters}}, Dumper=_ParamsDumper))
    return [
        sys.executable,
        "-m",
        NODE_KINDS[spec.node],
        "--ros-args",
        "-r",
        f"__node:={spec.name}",
        "--params-file",
        str(params_file),
    ]


class Graph:
    """Running node processes; `stop()` shuts them down upstream first (`stop_order`)."""

    def __init__(self, spec: GraphSpec, log_dir: Path | None = None) -> None:
        self.spec = spec
        self.log_dir = log_dir
        self.processes: dict[str, subprocess.Popen] = {}
        # The nodes' parameter files; removed by `stop()`, once no node can still be reading them.
        self.params_dir = Path(tempfile.mkdtemp(prefix="playseg-up-"))

    def start(self) -> None:
        env = dict(os.environ)
        if self.spec.ros_domain_id is not None:
            env["ROS_DOMAIN_ID"] = str(self.spec.ros_domain_id)
        for spec in self.spec.nodes:
            out = None
            if self.log_dir is not None:
                self.log_dir.mkdir(parents=True, exist_ok=True)
                out = open(self.log_dir / f"{spec.name}.log", "wb")  # noqa: SIM115 (owned by the child)
            # Own process group: a terminal's Ctrl-C reaches only us, and we stop the nodes in order.
            self.processes[spec.name] = subprocess.Popen(
                node_command(spec, self.params_dir),
                env=env,
                stdout=out,
                stderr=subprocess.STDOUT if out else None,
                start_new_session=True,
            )

    def wait(self, poll_s: float = 0.2) -> str | None:
        """Block until a node exits; returns its name (or None if all are still running on signal)."""
        ends = {s.name for s in self.spec.nodes if s.exit_ends_graph}
        while True:
            for name, proc in self.processes.items():
                if proc.poll() is not None and (name in ends or proc.returncode != 0):
                    return name
            if all(p.poll() is not None for p in self.processes.values()):
                return None
            time.sleep(poll_s)

    def stop(self) -> dict[str, int]:
        """Stop the nodes upstream first, each once the nodes publishing to it have exited: a stopping
        node hands on what it still holds (a topic_adapter its last steps, a segmenter its last
        segments), and its readers are still running to take it. SIGINT, then escalate after
        `shutdown_timeout_s`; returns each node's exit code."""
        for spec in stop_order(self.spec):
            proc = self.processes.get(spec.name)
            if proc is None:
                continue
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=self.spec.shutdown_timeout_s)
            except subprocess.TimeoutExpired:
                print(
                    f"[up] {spec.name} did not stop within {self.spec.shutdown_timeout_s} s: terminating",
                    file=sys.stderr,
                )
                proc.terminate()
                try:
                    proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        shutil.rmtree(self.params_dir, ignore_errors=True)
        return {name: proc.returncode for name, proc in self.processes.items()}


def player_graph(bag: Path, log_dir: Path, **parameters) -> Graph:
    """A graph of one bag_player node playing ``bag`` (exits when done), with its other ``parameters``."""
    spec = NodeSpec("bag_player", "bag_player", {"bag": str(bag), "exit_when_done": True, **parameters})
    return Graph(GraphSpec([spec]), log_dir=log_dir)


def run_graph(path: str | Path) -> int:
    """`playseg up`: start the graph, wait for Ctrl-C or a graph-ending node, stop everything."""
    spec = load_graph(path)
    graph = Graph(spec)

    def request_stop(signum, frame):  # noqa: ARG001
        raise KeyboardInterrupt

    # Installed explicitly for SIGINT too: a shell starts a background job with SIGINT ignored, and the
    # nodes would inherit that (and miss the launcher's SIGINT while they start up).
    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    print(f"[up] starting {len(spec.nodes)} nodes: {', '.join(s.name for s in spec.nodes)}", file=sys.stderr)
    for line in spec.wired:
        print(f"[up] waits for this graph's subscribers: {line}", file=sys.stderr)
    ended = None
    try:
        graph.start()
        ended = graph.wait()
    except KeyboardInterrupt:
        print("[up] stopping ...", file=sys.stderr)
    finally:
        # A second Ctrl-C must not abandon the nodes half-stopped: stopping always runs to its end.
        for sig in previous:
            signal.signal(sig, signal.SIG_IGN)
        codes = graph.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if ended:
        print(f"[up] {ended} exited (code {codes[ended]}): graph stopped", file=sys.stderr)
    failed = {n: c for n, c in codes.items() if c not in (0, -signal.SIGINT)}
    for name, code in failed.items():
        print(f"[up] {name} exited with code {code}", file=sys.stderr)
    return 1 if failed else 0
