"""The trainer's persistent augmentation buffer: an append-only, crash-safe log of labelled segments.

Layout: one file ``segments.log`` of records ``MAGIC | u32 header_len | u64 payload_len | u32 crc32 |
header (JSON) | payload (raw arrays)``. ``append`` returns only after the record is flushed and fsync'ed,
so every segment the trainer acknowledged survives a crash. On open, a torn record at the tail (a crash
mid-write) is cut off; a corrupt record elsewhere is an error naming the file and byte offset.
Each record is one `SegmentClip`; the header holds its episode id, source and segment fields (start,
end, instruction, confidence, log_prob), the payload its arrays by feature name (``action``,
``observation.state`` and every ``observation.images.<camera>`` present). Records written before feature
names (arrays ``actions``, ``states``, ``frames``) are read as well.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from playseg_core.data.episode import Segment, SegmentClip
from playseg_core.data.features import ACTION, DEFAULT_CAMERA, STATE
from playseg_core.errors import PlaysegError

MAGIC = b"PSB1"
_PREFIX = struct.Struct("<4sIQI")  # magic, header length, payload length, crc32 of header + payload
LOG_NAME = "segments.log"


_LEGACY_ARRAYS = {"actions": ACTION, "states": STATE, "frames": DEFAULT_CAMERA}


class AugmentationBuffer:
    """Append-only segment store in ``directory`` (created if missing)."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.path = self.directory / LOG_NAME
        self._offsets: list[int] = []
        self._keys: set[tuple[str, int, int, str]] = set()
        self._steps = 0
        self.recovered_bytes = self._scan_and_repair()
        self._file = open(self.path, "ab")  # noqa: SIM115 (kept open for the buffer's lifetime)

    def __len__(self) -> int:
        return len(self._offsets)

    @property
    def num_steps(self) -> int:
        """Total actions over all buffered segments."""
        return self._steps

    def __contains__(self, clip: object) -> bool:
        """Whether a segment with the same episode, start, end and source is stored already."""
        return isinstance(clip, SegmentClip) and _key(clip) in self._keys

    def append(self, clip: SegmentClip) -> int:
        """Write one segment durably; returns its index once it is on disk."""
        seg = clip.segment
        header: dict = {
            "episode_id": clip.episode_id,
            "start": seg.start,
            "end": seg.end,
            "instruction": seg.instruction,
            "confidence": float(seg.confidence),
            "log_prob": float(seg.log_prob),
            "source": clip.source,
        }
        chunks, arrays = [], {}
        named = {
            ACTION: clip.actions,
            **({STATE: clip.state} if clip.state is not None else {}),
            **clip.images,
        }
        for name, array in named.items():
            array = np.ascontiguousarray(array)
            arrays[name] = {"dtype": array.dtype.str, "shape": list(array.shape)}
            chunks.append(array.tobytes())
        header["arrays"] = arrays
        header_bytes = json.dumps(header, separators=(",", ":")).encode()
        payload = b"".join(chunks)
        crc = zlib.crc32(payload, zlib.crc32(header_bytes))
        offset = self._file.tell()
        self._file.write(_PREFIX.pack(MAGIC, len(header_bytes), len(payload), crc) + header_bytes + payload)
        self._file.flush()
        os.fsync(self._file.fileno())
        self._offsets.append(offset)
        self._keys.add(_key(clip))
        self._steps += seg.length
        return len(self._offsets) - 1

    def __getitem__(self, index: int) -> SegmentClip:
        with open(self.path, "rb") as f:
            f.seek(self._offsets[index])
            return _read_record(f, self.path)[0]

    def __iter__(self) -> Iterator[SegmentClip]:
        self._file.flush()
        with open(self.path, "rb") as f:
            for offset in self._offsets:
                f.seek(offset)
                yield _read_record(f, self.path)[0]

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> AugmentationBuffer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _scan_and_repair(self) -> int:
        """Index every complete record; cut a torn tail. Returns the number of bytes cut."""
        if not self.path.exists():
            return 0
        size = self.path.stat().st_size
        good_end = 0
        with open(self.path, "rb") as f:
            while good_end < size:
                try:
                    clip, next_offset = _read_record(f, self.path)
                except _TornRecord:
                    break
                self._offsets.append(good_end)
                self._keys.add(_key(clip))
                self._steps += clip.segment.length
                good_end = next_offset
        if good_end < size:
            with open(self.path, "r+b") as f:
                f.truncate(good_end)
        return size - good_end


MODEL_DIGEST_SEP = "@sha256:"
"""A source ``<name>@sha256:<hex>`` (the segmenter's model_id) names the model by its checkpoint digest."""
MODEL_DIGEST_CHARS = 16


def _key(clip: SegmentClip) -> tuple[str, int, int, str]:
    """What makes a segment the same one: episode, start, end and the model that found it, by its
    checkpoint digest where the source carries one (two segmenters, or two copies of one checkpoint)."""
    source = clip.source
    if MODEL_DIGEST_SEP in source:
        source = MODEL_DIGEST_SEP + source.rsplit(MODEL_DIGEST_SEP, 1)[1]
    return clip.episode_id, clip.segment.start, clip.segment.end, source


class _TornRecord(Exception):
    """The file ends inside a record (a crash mid-append)."""


def _read_record(f, path: Path) -> tuple[SegmentClip, int]:
    offset = f.tell()
    prefix = f.read(_PREFIX.size)
    if len(prefix) < _PREFIX.size:
        raise _TornRecord
    magic, header_len, payload_len, crc = _PREFIX.unpack(prefix)
    if magic != MAGIC:
        raise PlaysegError(f"{path}: no record at byte {offset} (bad magic {magic!r})")
    body = f.read(header_len + payload_len)
    if len(body) < header_len + payload_len:
        raise _TornRecord
    header_bytes, payload = body[:header_len], body[header_len:]
    if zlib.crc32(payload, zlib.crc32(header_bytes)) != crc:
        # A bad checksum on the very last record is a torn write; earlier it is corruption.
        if f.read(1) == b"":
            raise _TornRecord
        raise PlaysegError(f"{path}: record at byte {offset} fails its checksum")
    header = json.loads(header_bytes)
    arrays, cursor = {}, 0
    for name, spec in header.pop("arrays").items():
        dtype = np.dtype(spec["dtype"])
        count = int(np.prod(spec["shape"], dtype=np.int64))
        arrays[_LEGACY_ARRAYS.get(name, name)] = np.frombuffer(payload, dtype, count, cursor).reshape(
            spec["shape"]
        )
        cursor += count * dtype.itemsize
    try:
        segment = Segment(
            header.pop("start"),
            header.pop("end"),
            header.pop("instruction"),
            header.pop("confidence"),
            header.pop("log_prob"),
        )
        clip = SegmentClip(
            segment=segment,
            actions=arrays.pop(ACTION),
            state=arrays.pop(STATE, None),
            images=arrays,
            episode_id=header.pop("episode_id"),
            source=header.pop("source", ""),
        )
    except (KeyError, TypeError, ValueError) as error:
        raise PlaysegError(f"{path}: record at byte {offset} is not a segment: {error}") from None
    return clip, offset + _PREFIX.size + header_len + payload_len
