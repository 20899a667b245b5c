"""Robot bags as `rosbags` reads them: rosbag2 (mcap or sqlite3, zstd-compressed, split into several
files), a single .mcap/.db3 storage file, or a ROS 1 .bag; and the messages of the topics a mapping reads.

Message times: with ``clock: header`` (the default) a message's ``header.stamp`` when it has a non-zero
one, otherwise the time the recorder received it; with ``clock: receive`` always the latter.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys.store import Typestore

from playseg_core.errors import PlaysegError
from playseg_core.yaml_io import YamlFileError, load_yaml
from playseg_ros.bag.mcap_scan import damage_of
from playseg_ros.bag.schema import METADATA_FILE
from playseg_ros.convert.errors import ConvertError
from playseg_ros.typestore import playseg_typestore

STORAGE_SUFFIXES = (".mcap", ".db3")
ROS1_SUFFIX = ".bag"
TIMED_ANNOTATION = "playseg_msgs/msg/TimedAnnotation"
PLAY_STEP = "playseg_msgs/msg/PlayStep"
PLAY_STEPS_TOPIC = "/play/steps"


def convert_typestore() -> Typestore:
    """ROS 2 Kilted's standard types plus playseg_msgs (typestore.py; TimedAnnotation included): how a
    bag without embedded definitions is read."""
    return playseg_typestore()


def is_bag(path: Path) -> bool:
    """A rosbag2 directory, a rosbag2 storage file or a ROS 1 bag file."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix in (*STORAGE_SUFFIXES, ROS1_SUFFIX)


def find_bags(inputs: Sequence[str | Path]) -> list[Path]:
    """The bags named by ``inputs``: bags themselves, or directories searched for bags (a bag directory's
    own files are not bags of their own). FileNotFoundError for an input that does not exist."""
    found: list[Path] = []
    for raw in inputs:
        path = Path(raw)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such bag or directory")
        if is_bag(path):
            found.append(path)
        elif path.is_dir():
            found.extend(_bags_under(path))
        else:
            raise PlaysegError(f"{path}: not a bag (expected a rosbag2 directory, .mcap, .db3 or .bag)")
    unique = list(dict.fromkeys(p.resolve() for p in found))
    return unique


def _bags_under(root: Path) -> Iterator[Path]:
    for child in sorted(root.iterdir()):
        if child.name.startswith("."):
            continue  # staging and hidden directories (ours included)
        if is_bag(child):
            yield child
        elif child.is_dir():
            yield from _bags_under(child)


def fingerprint(bag: Path) -> str:
    """Changes when a bag's files change (names, sizes, modification times): a re-recorded or recovered
    bag is converted again."""
    files = sorted(p for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else [bag]
    stats = [
        (str(p.relative_to(bag) if bag.is_dir() else p.name), p.stat().st_size, p.stat().st_mtime_ns)
        for p in files
    ]
    return hashlib.sha256(json.dumps(stats).encode()).hexdigest()[:32]


def bag_size(bag: Path) -> int:
    return (
        sum(p.stat().st_size for p in bag.rglob("*") if p.is_file()) if bag.is_dir() else bag.stat().st_size
    )


@contextmanager
def open_bag(bag: Path) -> Iterator[AnyReader]:
    """An open `AnyReader`; ConvertError naming the bag when it cannot be opened."""
    if bag.is_dir() and (bag / METADATA_FILE).is_file():
        try:  # first through the project's bounded loader: rosbags' own YAML parser has no limits
            load_yaml(bag / METADATA_FILE, METADATA_FILE)
        except YamlFileError as error:
            raise ConvertError(bag, str(error)) from None
    try:
        reader = AnyReader([bag], default_typestore=convert_typestore())
        reader.open()
    except Exception as error:  # noqa: BLE001 -- a damaged bag makes rosbags raise anything
        raise ConvertError(bag, damage(bag) or f"cannot open: {type(error).__name__}: {error}") from None
    try:
        yield reader
    finally:
        reader.close()


def damage(bag: Path) -> str | None:
    """Where an MCAP file of ``bag`` is damaged (file and reason), when one is."""
    files = sorted(bag.glob("*.mcap")) if bag.is_dir() else [bag] if bag.suffix == ".mcap" else []
    for file in files:
        detail, topic = damage_of(file)
        if detail:
            return f"file {file.name!r}" + (f", topic {topic!r}" if topic else "") + f": {detail}"
    return None


def topic_types(reader: AnyReader) -> dict[str, str]:
    """Topic -> message type (``pkg/msg/Type``)."""
    return {name: info.msgtype or "" for name, info in reader.topics.items()}


def is_play_bag(bag: Path) -> bool:
    """A playseg play bag (PlaySteps on /play/steps): read as it is, without a mapping. A bag that cannot be
    opened (damaged, truncated) is a ConvertError saying why, not "no play bag"."""
    with open_bag(bag) as reader:
        return topic_types(reader).get(PLAY_STEPS_TOPIC) == PLAY_STEP


@dataclass
class TopicSamples:
    """The messages of one topic in time order: ``stamps`` (int64 ns) and the deserialized messages."""

    topic: str
    msgtype: str
    stamps: np.ndarray
    messages: list[Any]
    arrival: np.ndarray | None = None  # each sample's index in recording (log time) order


def message_time(msg: Any, received_ns: int, use_header: bool) -> int:
    if use_header:
        header = getattr(msg, "header", None)
        stamp = getattr(header, "stamp", None)
        if stamp is not None:
            ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
            if ns:
                return ns
    return received_ns


def read_topics(
    bag: Path, reader: AnyReader, topics: Iterable[str], use_header: bool, optional: Iterable[str] = ()
) -> dict[str, TopicSamples]:
    """All messages of ``topics``, deserialized (large arrays stay views into the bag's buffers); a topic
    that is missing (unless ``optional``: then it has no samples), of a type without definition or with an
    undeserializable message is a ConvertError."""
    types = topic_types(reader)
    absent = [t for t in set(optional) if t not in types]
    wanted = sorted(set(topics) - set(absent))
    for topic in wanted:
        if topic not in types:
            raise ConvertError(
                bag, f"topic missing (the bag has {', '.join(sorted(types)) or 'no topics'})", topic
            )
        if types[topic] not in reader.typestore.fielddefs:
            raise ConvertError(
                bag, f"unknown message type {types[topic]!r} (no definition in the bag)", topic
            )
    connections = [c for c in reader.connections if c.topic in wanted]
    stamps: dict[str, list[int]] = {t: [] for t in wanted}
    messages: dict[str, list[Any]] = {t: [] for t in wanted}
    iterator = reader.messages(connections)
    received = 0
    while True:
        try:
            connection, received, raw = next(iterator)
        except StopIteration:
            break
        except Exception as error:  # noqa: BLE001 -- a damaged file makes the storage reader raise anything
            # the storage library's own words name no file or offset; the record scan does
            where = damage(bag) or f"{type(error).__name__}: {error}"
            raise ConvertError(
                bag,
                f"unreadable after {sum(map(len, stamps.values()))} messages: {where}",
                time_ns=received or None,
            ) from None
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as error:  # noqa: BLE001
            raise ConvertError(
                bag, f"cannot deserialize: {error}", connection.topic, time_ns=received
            ) from None
        stamps[connection.topic].append(message_time(msg, received, use_header))
        messages[connection.topic].append(msg)
    samples = {}
    for topic in wanted:
        times = np.asarray(stamps[topic], dtype=np.int64)
        order = np.argsort(times, kind="stable")
        samples[topic] = TopicSamples(
            topic, types[topic], times[order], [messages[topic][i] for i in order], order
        )
    for topic in absent:
        samples[topic] = TopicSamples(topic, "", np.zeros(0, dtype=np.int64), [])
    return samples
