"""Reading a possibly damaged .mcap file record by record: what recovery keeps and what error messages
point at.

Every MCAP record is framed by an opcode and a length, so a scan can tell a complete record from one cut
short without parsing it, and a record is parsed only from its own bytes: a truncated or damaged file
ends the scan at the first record that is incomplete or does not parse (chunks are also checked against
their CRC), never with the parser's error (`struct.error`, zstd errors, ...).
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import get_chunk_data_stream

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length of the record body
_OPCODES = frozenset(int(opcode) for opcode in Opcode)
_FOOTER_BODY = 20  # summary start, summary offset start, summary CRC
_READERS = {
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read,
    Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
    Opcode.HEADER: Header.read,
    Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.METADATA: Metadata.read,
    Opcode.METADATA_INDEX: MetadataIndex.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.STATISTICS: Statistics.read,
    Opcode.SUMMARY_OFFSET: SummaryOffset.read,
}


class _BoundedStream(ReadDataStream):
    """mcap's stream returns short reads silently (struct.error later); here a short read is an error."""

    def read(self, length: int) -> bytes:
        data = super().read(length)
        if len(data) < length:
            raise EndOfFile()
        return data


def _parse(opcode: int, body: bytes) -> list[McapRecord]:
    stream = _BoundedStream(BytesIO(body))
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, len(body))]
    record = _READERS[Opcode(opcode)](stream)
    if isinstance(record, Chunk):
        return [record, *_chunk_records(record)]  # the chunk itself marks its offset
    return [record]


_CHUNK_RECORDS = frozenset((Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE))


def _chunk_records(chunk: Chunk) -> list[McapRecord]:
    """The records inside ``chunk``, each parsed from its own bytes. mcap's `breakup_chunk` reads a schema
    or channel by its fields and ignores its length, so a damaged length passes it but not rosbags (an
    OverflowError with no offset): here a length that does not fit the chunk is damage."""
    stream, size = get_chunk_data_stream(chunk, validate_crc=True)
    records: list[McapRecord] = []
    while stream.count < size:
        at = stream.count
        if size - at < _RECORD_HEAD.size:
            raise EndOfFile()
        opcode, length = _RECORD_HEAD.unpack(stream.read(_RECORD_HEAD.size))
        if length > size - stream.count:
            raise ValueError(
                f"the record at byte {at} inside it claims {length} bytes, {size - stream.count} left"
            )
        body = stream.read(length)
        if opcode in _CHUNK_RECORDS:  # others are skipped, as the MCAP spec asks of unknown records
            records += _parse(opcode, body)
    return records


@dataclass
class RecordScan:
    """The complete, intact records of an .mcap file from its start, up to its footer or the first record
    that is cut short or damaged.

    Iterating yields ``(offset, record)``: the byte offset of the top-level record it came from (a
    chunk's records carry the chunk's offset, right after the Chunk record itself). Afterwards ``end`` is
    the offset just past the last good record and ``problem`` says why the scan stopped (None: the file
    ended with a footer and the closing magic). ``start``: the offset of a record to begin at (an earlier
    scan's ``end``: a file still being written is read on from where the last scan stopped).
    """

    path: Path
    end: int = 0
    problem: str | None = None
    start: int = 0
    damaged: bool = False  # the scan stopped at bytes that are not MCAP (not at a cut): more may follow

    def __iter__(self) -> Iterator[tuple[int, McapRecord]]:
        self.end, self.problem, self.damaged = 0, None, False
        with self.path.open("rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            if stream.read(len(MAGIC)) != MAGIC:
                self.problem = "cut inside its magic" if size < len(MAGIC) else "no MCAP magic at its start"
                return
            offset = self.end = max(self.start, len(MAGIC))
            stream.seek(offset)
            while True:
                head = stream.read(_RECORD_HEAD.size)
                if not head:
                    self.problem = f"ends after its last complete record at byte {offset}, without a footer"
                    return
                if len(head) < _RECORD_HEAD.size:
                    self.problem = f"cut inside the record at byte {offset}"
                    return
                opcode, length = _RECORD_HEAD.unpack(head)
                if opcode not in _OPCODES:
                    self.problem = f"unknown record (opcode {opcode:#04x}) at byte {offset}: damaged data"
                    self.damaged = True
                    return
                kind = Opcode(opcode).name.lower()
                if offset + _RECORD_HEAD.size + length > size:
                    self.problem = f"cut inside the {kind} record at byte {offset}"
                    return
                body = stream.read(length)
                try:
                    records = _parse(opcode, body)
                except Exception as error:  # noqa: BLE001 -- damaged bytes make any parser error possible
                    self.problem = f"damaged {kind} record at byte {offset}: {type(error).__name__}: {error}"
                    self.damaged = True
                    return
                for record in records:
                    yield offset, record
                offset = self.end = offset + _RECORD_HEAD.size + length
                if opcode == Opcode.FOOTER:
                    if stream.read(len(MAGIC)) != MAGIC:
                        self.problem = "cut inside its closing magic"
                    return


def read_record(path: Path, offset: int) -> list[McapRecord]:
    """The record at ``offset`` (one a scan found complete), a chunk broken up into its records."""
    with path.open("rb") as stream:
        stream.seek(offset)
        opcode, length = _RECORD_HEAD.unpack(stream.read(_RECORD_HEAD.size))
        return _parse(opcode, stream.read(length))


def mcap_files(directory: Path) -> list[Path]:
    """The .mcap files of a bag directory in recording order (``<name>_<index>.mcap``)."""

    def index(path: Path) -> tuple[int, str]:
        match = re.search(r"_(\d+)\.mcap$", path.name)
        return (int(match.group(1)) if match else -1, path.name)

    return sorted(directory.glob("*.mcap"), key=index)


def has_footer(path: Path) -> bool:
    """Whether the file ends like a finished MCAP file (footer record, then the magic)."""
    try:
        with path.open("rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            if size < 2 * len(MAGIC) + _RECORD_HEAD.size + _FOOTER_BODY:
                return False
            stream.seek(size - len(MAGIC) - _RECORD_HEAD.size - _FOOTER_BODY)
            tail = stream.read()
    except OSError:
        return False
    opcode, length = _RECORD_HEAD.unpack(tail[: _RECORD_HEAD.size])
    return tail[-len(MAGIC) :] == MAGIC and opcode == Opcode.FOOTER and length == _FOOTER_BODY


def damage_of(path: Path) -> tuple[str, str | None]:
    """Why ``path`` cannot be read, for an error message: (detail, the topic when one is known).

    A file without footer is reported as truncated/unfinished (recoverable); otherwise the first damaged
    record, with its byte offset and, for a chunk, the topics it held (from the file's chunk index).
    """
    if not path.is_file():
        return "file is missing", None
    if not has_footer(path):
        return (
            f"the file is truncated or unfinished (no MCAP footer at its end, {path.stat().st_size} bytes): "
            "`playseg bag recover` restores every complete message",
            None,
        )
    scan = RecordScan(path)
    for _ in scan:  # only where the scan stops matters
        pass
    if scan.problem is None:
        return "", None
    topics = _chunk_topics(path, scan.end)
    where = f" (topics {', '.join(topics)})" if len(topics) > 1 else ""
    return f"{scan.problem}{where}", topics[0] if len(topics) == 1 else None


def _chunk_topics(path: Path, chunk_offset: int) -> list[str]:
    """The topics of the chunk at ``chunk_offset`` according to the summary (none when unreadable)."""
    with contextlib.suppress(Exception), path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
        if summary is not None:
            for index in summary.chunk_indexes:
                if index.chunk_start_offset == chunk_offset:
                    ids = sorted(index.message_index_offsets)
                    return sorted({summary.channels[i].topic for i in ids if i in summary.channels})
    return []
