"""The reviewed segments as an MCAP file Foxglove shows on its timeline, beside the original bag.

Two JSON channels, at the recording's times (a converted bag's episodes: its first message time plus
each observation's `timestamp`, so the file lines up with the bag when both are opened):

    /playseg/instruction   {"data": <instruction>} at every observation ("" outside a segment): the
                           State Transitions panel draws it as bands
    /playseg/boundaries    foxglove.Log at each segment's start and end ("start: <instruction>",
                           "end: <instruction>"; name = the episode id)
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Segment

INSTRUCTION_TOPIC = "/playseg/instruction"
BOUNDARY_TOPIC = "/playseg/boundaries"
LOG_INFO = 2
"""foxglove.Log level INFO."""

INSTRUCTION_SCHEMA = {"type": "object", "properties": {"data": {"type": "string"}}}
LOG_SCHEMA = {
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "level": {"type": "integer"},
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer"},
    },
}


def episode_times_ns(dataset: PlayDataset, index: int) -> np.ndarray:
    """Episode ``index``'s observation times in nanoseconds on the recording's clock."""
    source = dataset.records[index].source or {}
    start = int(source.get("start_ns", 0)) if isinstance(source.get("start_ns", 0), int) else 0
    return start + np.round(np.asarray(dataset.timestamps(index)) * 1e9).astype(np.int64)


def write_segments_mcap(dataset: PlayDataset, segments: Mapping[int, Sequence[Segment]], out: Path) -> int:
    """Write ``segments`` (episode index -> its labelled segments) to ``out``; returns the message count."""
    from mcap.writer import Writer

    records: list[tuple[int, int, bytes]] = []  # (time, channel, data)
    for index, found in segments.items():
        times = episode_times_ns(dataset, index)
        steps = step_instructions(found, len(times))
        records += [
            (int(t), 0, json.dumps({"data": text}).encode()) for t, text in zip(times, steps, strict=True)
        ]
        for segment in found:
            for edge, step in (("start", segment.start), ("end", segment.end)):
                t = int(times[step])
                log = {"timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}, "level": LOG_INFO,
                       "message": f"{edge}: {segment.instruction}", "name": dataset.records[index].episode_id,
                       "file": "", "line": 0}  # fmt: skip
                records.append((t, 1, json.dumps(log).encode()))
    records.sort(key=lambda record: (record[0], record[1]))
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.with_name(f".{out.name}.partial")
    with open(staging, "wb") as handle:
        writer = Writer(handle)
        writer.start(profile="", library="playseg review")
        instruction = writer.register_schema(
            "playseg.Instruction", "jsonschema", json.dumps(INSTRUCTION_SCHEMA).encode()
        )
        log = writer.register_schema("foxglove.Log", "jsonschema", json.dumps(LOG_SCHEMA).encode())
        channels = [
            writer.register_channel(INSTRUCTION_TOPIC, "json", instruction),
            writer.register_channel(BOUNDARY_TOPIC, "json", log),
        ]
        for sequence, (t, channel, data) in enumerate(records):
            writer.add_message(channels[channel], log_time=t, data=data, publish_time=t, sequence=sequence)
        writer.finish()
    staging.replace(out)
    return len(records)


def step_instructions(segments: Sequence[Segment], observations: int) -> list[str]:
    """The instruction in force at each observation: a segment [s, e) holds o_s..o_e-1; its end observation
    belongs to the next one (or to none)."""
    steps = [""] * observations
    for segment in segments:
        steps[segment.start : segment.end] = [segment.instruction] * (segment.end - segment.start)
    return steps
