"""What `playseg up` knows of a graph before it starts it: which topics each node publishes and subscribes
to (from its kind and parameters, as the node itself will resolve them), so that

- a node that starts a volatile stream waits for the subscribers the graph will have (`wire_waits`): the
  bag_player for the subscriptions to each topic it plays and to /clock, topic_adapter and play_source
  for the readers of their PlaySteps, the segmenter for the readers of its segments (it subscribes to
  steps only then, so the chain starts downstream first);
- the graph stops upstream first (`stop_order`): a node is stopped once every node publishing to it has
  exited, so what a stopping node hands on (the adapter's last steps, the segmenter's last segments)
  reaches readers that are still running.

A wait a config sets by hand is kept. No rclpy here: it runs in the launcher, before any node exists.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field


@dataclass
class NodeSpec:
    """One node of a graph config (launch.py parses it)."""

    name: str
    node: str
    parameters: dict = field(default_factory=dict)
    exit_ends_graph: bool = False


@dataclass
class GraphSpec:
    """A graph config: its nodes and how the graph runs."""

    nodes: list[NodeSpec]
    ros_domain_id: int | None = None
    shutdown_timeout_s: float = 15.0
    wired: list[str] = field(default_factory=list)  # the waits `playseg up` set, one line per node


CLOCK = "/clock"

TOPIC_DEFAULTS: dict[str, dict[str, str | list[str]]] = {
    "play_source": {
        "steps_topic": "/play/steps",
        "annotations_topic": "/play/annotations",
        "ground_truth_topic": "/play/ground_truth",
    },
    "topic_adapter": {"steps_topic": "/play/steps", "annotations_topic": "/play/annotations"},
    "segmenter": {"steps_topic": "/play/steps", "segments_topic": "/segments"},
    "trainer": {"segments_topic": "/segments", "status_topic": "/trainer/status"},
    "recorder": {"topics": ["/play/steps"]},
}
"""The nodes' topic parameters and their defaults (the values each node declares)."""

WAITED_OUTPUT = {"topic_adapter": "steps_topic", "play_source": "steps_topic", "segmenter": "segments_topic"}
"""Node kind -> the output whose subscriber count its `wait_for_subscribers` waits for."""


@dataclass
class Ports:
    """One node's topics: those it publishes, and how many subscriptions it makes to each it reads."""

    publishes: set[str] = field(default_factory=set)
    subscribes: Counter[str] = field(default_factory=Counter)


def graph_name(topic: str, node_name: str) -> str:
    """The topic's fully qualified name for a node of `playseg up` (root namespace)."""
    if topic.startswith("~"):
        return f"/{node_name}{topic[1:]}"
    return topic if topic.startswith("/") else f"/{topic}"


def node_ports(spec: NodeSpec) -> Ports:
    """The topics of one node of the graph. A file the node reads (a bag, a mapping) that cannot be read
    leaves its topics out: the node itself reports it when it starts."""
    params = {**TOPIC_DEFAULTS.get(spec.node, {}), **spec.parameters}
    ports = Ports()

    def topic(name: str) -> str | None:
        value = params.get(name)
        return graph_name(value, spec.name) if isinstance(value, str) and value else None

    if spec.node in ("play_source", "topic_adapter"):
        ports.publishes |= {
            t for t in map(topic, ("steps_topic", "annotations_topic", "ground_truth_topic")) if t
        }
    if spec.node == "segmenter":
        ports.subscribes.update(t for t in [topic("steps_topic")] if t)
        ports.publishes |= {t for t in [topic("segments_topic")] if t}
    if spec.node == "trainer":
        ports.subscribes.update(t for t in [topic("segments_topic")] if t)
        ports.publishes |= {t for t in [topic("status_topic")] if t}
    if spec.node == "recorder":
        listed = params.get("topics") if isinstance(params.get("topics"), list) else []
        ports.subscribes.update({graph_name(t, spec.name) for t in listed if isinstance(t, str) and t})
    if spec.node == "topic_adapter":
        ports.subscribes.update(_mapping_topics(params.get("mapping")))
        if params.get("use_sim_time") is True:
            ports.subscribes[CLOCK] += 1  # its own /clock reader, besides its time source's
    if spec.node == "bag_player":
        ports.publishes |= set(_played_topics(params))
        if params.get("clock") is True:
            ports.publishes.add(CLOCK)
    if params.get("use_sim_time") is True:
        ports.subscribes[CLOCK] += 1  # rclpy's time source
    return ports


def _mapping_topics(path: object) -> list[str]:
    from playseg_ros.convert.errors import MappingError
    from playseg_ros.convert.mapping import load_mapping

    if not isinstance(path, str) or not path:
        return []
    try:
        return [graph_name(t, "") for t in load_mapping(path).topics]
    except (MappingError, OSError, ValueError):
        return []


def _played_topics(params: dict) -> list[str]:
    from playseg_ros.bag import BagError, BagReader

    listed = [t for t in params.get("topics") or [] if isinstance(t, str) and t]
    if listed:
        return listed
    bag = params.get("bag")
    if not isinstance(bag, str) or not bag:
        return []
    try:
        with BagReader(bag) as reader:
            return list(reader.topics)
    except (BagError, OSError, ValueError):
        return []


def _readers(spec: GraphSpec, ports: dict[str, Ports], publisher: str) -> Counter[str]:
    """Subscriptions the other nodes of the graph make to what `publisher` publishes, by topic."""
    counts: Counter[str] = Counter()
    for node in spec.nodes:
        if node.name != publisher:
            for topic, n in ports[node.name].subscribes.items():
                if topic in ports[publisher].publishes:
                    counts[topic] += n
    return counts


def wire_waits(spec: GraphSpec) -> list[str]:
    """Set each stream source's wait for the subscribers the graph will have, unless the config sets it;
    returns what was set, one line per node."""
    ports = {node.name: node_ports(node) for node in spec.nodes}
    before = {node.name: dict(node.parameters) for node in spec.nodes}
    for node in spec.nodes:
        params = node.parameters
        readers = _readers(spec, ports, node.name)
        if node.node == "bag_player":
            if "wait_for_subscribers" in params or "wait_topics" in params or not readers:
                continue
            params["wait_for_subscribers"] = 1
            params["wait_topics"] = [f"{topic}={n}" for topic, n in sorted(readers.items())]
        elif node.node in WAITED_OUTPUT:
            key = WAITED_OUTPUT[node.node]
            output = graph_name(str(params.get(key) or TOPIC_DEFAULTS[node.node][key]), node.name)
            if "wait_for_subscribers" not in params and readers[output]:
                params["wait_for_subscribers"] = readers[output]
    return [
        f"{node.name}: "
        + ", ".join(f"{k}={v}" for k, v in node.parameters.items() if before[node.name].get(k) != v)
        for node in spec.nodes
        if node.parameters != before[node.name]
    ]


def stop_order(spec: GraphSpec) -> list[NodeSpec]:
    """The nodes upstream first: each after every node that publishes to it (config order among equals;
    a cycle is broken in config order)."""
    ports = {node.name: node_ports(node) for node in spec.nodes}
    upstream = {
        node.name: {
            other.name
            for other in spec.nodes
            if other.name != node.name and ports[other.name].publishes & set(ports[node.name].subscribes)
        }
        for node in spec.nodes
    }
    order: list[NodeSpec] = []
    left = list(spec.nodes)
    while left:
        done = {n.name for n in order}
        ready = next((n for n in left if upstream[n.name] <= done), left[0])
        order.append(ready)
        left.remove(ready)
    return order
