"""Reading a possibly damaged .mcap file record by record: what recovery keeps and what error messages
point at.

Every MCAP record is framed by an opcode and a length, so a scan can tell a complete record from one cut
short without parsing it, and a record is parsed only from its own bytes: a truncated or damaged file
ends the scan at the first record that is incomplete or does not parse (chunks are also checked against
their CRC), never with the parser's error (`struct.error`, zstd errors, ...).

With ``resync`` (recovery) the scan does not end there: it looks for the next chunk past the damaged
record (opcode, a length inside the file, a non-zero CRC that matches its content: a false match is a
2^-32 chance) and goes on from it, noting the bytes it skipped. Only when no chunk follows is the damage
the file's end: a cut (a clean tail) when the record ran past the end of the file, damage otherwise. A
damaged length field looks like a cut (the record seems to run past the end) until a chunk is found past
it; a chunk whose length field alone is damaged is read with the length its own fields give (compression
name and data length) when that makes it intact, CRC included.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

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

from playseg_core.errors import PlaysegError

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length of the record body
_OPCODES = frozenset(int(opcode) for opcode in Opcode)
_FOOTER_BODY = 20  # summary start, summary offset start, summary CRC
_CHUNK_MIN_BODY = 8 + 8 + 8 + 4 + 4 + 8  # times, size, CRC, empty compression string, records length
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


def _parse(opcode: int, body: bytes, exact: bool = False) -> list[McapRecord]:
    """The record(s) of ``body``; ``exact``: a record that does not use all of its bytes is damage (a
    damaged length the parser would step over, landing in the middle of the next records)."""
    stream = _BoundedStream(BytesIO(body))
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, len(body))]
    record = _READERS[Opcode(opcode)](stream)
    if exact and stream.count != len(body):
        raise PlaysegError(f"the record uses {stream.count} of its {len(body)} bytes")
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
            raise PlaysegError(
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
    damaged: bool = False  # damaged bytes (not a cut) were met: skipped (resync) or where the scan stopped
    resync: bool = False  # go on at the next intact chunk past a damaged record (recovery)
    ended_damaged: bool = False  # the scan stopped at damaged bytes, not at a cut or the footer
    skipped: list[tuple[int, int, str]] = field(default_factory=list)  # (start, end, why): bytes passed over

    @property
    def skipped_bytes(self) -> int:
        return sum(end - start for start, end, _ in self.skipped)

    def __iter__(self) -> Iterator[tuple[int, McapRecord]]:
        self.end, self.problem, self.damaged, self.skipped, self.ended_damaged = 0, None, False, [], False
        with self.path.open("rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            if stream.read(len(MAGIC)) != MAGIC:
                self.problem = "cut inside its magic" if size < len(MAGIC) else "no MCAP magic at its start"
                return
            offset = self.end = max(self.start, len(MAGIC))
            chunked = False  # a chunk was seen: messages outside chunks are damage (resync)
            stream.seek(offset)
            while True:
                head = stream.read(_RECORD_HEAD.size)
                if not head:
                    self.problem = f"ends after its last complete record at byte {offset}, without a footer"
                    return
                problem, damaged, records, length = None, True, [], 0
                if len(head) < _RECORD_HEAD.size:
                    problem, damaged = f"cut inside the record at byte {offset}", False
                else:
                    opcode, length = _RECORD_HEAD.unpack(head)
                    kind = Opcode(opcode).name.lower() if opcode in _OPCODES else ""
                    if opcode not in _OPCODES:
                        problem = f"unknown record (opcode {opcode:#04x}) at byte {offset}: damaged data"
                    elif offset + _RECORD_HEAD.size + length > size:
                        problem, damaged = f"cut inside the {kind} record at byte {offset}", False
                    else:
                        body = stream.read(length)
                        try:
                            records = _parse(opcode, body, exact=self.resync)
                            if self.resync and opcode == Opcode.MESSAGE and chunked:
                                # a chunked file keeps its messages in chunks: this is another record
                                # with a damaged opcode (a message index read as a message)
                                raise PlaysegError("a message record outside the chunks of a chunked file")
                            chunked = chunked or opcode == Opcode.CHUNK
                        except Exception as error:  # noqa: BLE001 -- damaged bytes make any parser error possible
                            # a parser's error is named (struct.error, ...); this module's says what it is
                            named = "" if isinstance(error, PlaysegError) else f"{type(error).__name__}: "
                            problem = f"damaged {kind} record at byte {offset}: {named}{error}"
                if (
                    problem is not None
                    and self.resync
                    and len(head) == _RECORD_HEAD.size
                    and opcode == Opcode.CHUNK
                ):
                    repaired = _chunk_by_its_sizes(stream, offset, size)
                    if repaired is not None:  # only the length field was hit: the chunk itself is intact
                        length, records = repaired
                        self.skipped.append(
                            (offset, offset, f"{problem}; read with the length its other fields give")
                        )
                        self.damaged, problem = True, None
                        stream.seek(offset + _RECORD_HEAD.size + length)
                if problem is not None:
                    following = _next_chunk(stream, offset + 1, size) if self.resync else None
                    if following is None:
                        self.problem, self.damaged = problem, self.damaged or damaged
                        self.ended_damaged = damaged
                        return
                    self.skipped.append((offset, following, problem))
                    self.damaged = True  # what looked like a cut had intact data after it
                    offset = self.end = following
                    stream.seek(offset)
                    continue
                for record in records:
                    yield offset, record
                offset = self.end = offset + _RECORD_HEAD.size + length
                if opcode == Opcode.FOOTER:
                    if stream.read(len(MAGIC)) != MAGIC:
                        self.problem = "cut inside its closing magic"
                    return


def _chunk_by_its_sizes(stream: BinaryIO, offset: int, size: int) -> tuple[int, list[McapRecord]] | None:
    """The chunk at ``offset`` whose record length and inner data length disagree, read with the one that
    makes it intact with a CRC (zstd ignores bytes after its frame, so both may): the one after which a
    plausible record (or the end of the file) follows wins. (That length, its records), else None."""
    fixed = 8 + 8 + 8 + 4  # times, uncompressed size, CRC
    stream.seek(offset)
    _, record_length = _RECORD_HEAD.unpack(stream.read(_RECORD_HEAD.size))
    candidates: list[tuple[int, Chunk]] = []
    stream.seek(offset + _RECORD_HEAD.size + fixed)
    name_length = struct.unpack("<I", stream.read(4).rjust(4, b"\xff"))[0]
    if name_length > 64:  # compression names are a few letters
        return None
    stream.seek(name_length, os.SEEK_CUR)
    data_length = struct.unpack("<Q", stream.read(8).rjust(8, b"\xff"))[0]
    by_fields = fixed + 4 + name_length + 8 + data_length
    if offset + _RECORD_HEAD.size + by_fields <= size:  # the record length may be the damaged one
        stream.seek(offset + _RECORD_HEAD.size)
        with contextlib.suppress(Exception):  # damaged bytes
            candidates.append((by_fields, Chunk.read(_BoundedStream(BytesIO(stream.read(by_fields))))))
    if offset + _RECORD_HEAD.size + record_length <= size:  # the data length may be the damaged one
        stream.seek(offset + _RECORD_HEAD.size)
        body = stream.read(record_length)
        with contextlib.suppress(struct.error, UnicodeDecodeError):
            start = fixed + 4 + name_length + 8
            times = struct.unpack_from("<QQQI", body, 0)
            chunk = Chunk(
                compression=body[fixed + 4 : fixed + 4 + name_length].decode(), data=body[start:],
                message_start_time=times[0], message_end_time=times[1], uncompressed_size=times[2],
                uncompressed_crc=times[3],
            )  # fmt: skip
            candidates.append((record_length, chunk))
    intact = [(length, chunk) for length, chunk in candidates if _intact_chunk(chunk)]
    for length, chunk in intact:
        end = offset + _RECORD_HEAD.size + length
        stream.seek(end)
        head = stream.read(_RECORD_HEAD.size)
        if not head or (
            len(head) == _RECORD_HEAD.size
            and head[0] in _OPCODES
            and end + _RECORD_HEAD.size + _RECORD_HEAD.unpack(head)[1] <= size
        ):
            return length, [chunk, *_chunk_records(chunk)]
    return None


def _next_chunk(stream: BinaryIO, start: int, size: int) -> int | None:
    """The offset of the first intact chunk record at or after ``start`` (see the module docstring)."""
    if start + _RECORD_HEAD.size + _CHUNK_MIN_BODY > size:
        return None
    with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
        at = data.find(bytes([Opcode.CHUNK]), start)
        while at >= 0:
            if at + _RECORD_HEAD.size <= size:
                _, length = _RECORD_HEAD.unpack_from(data, at)
                end = at + _RECORD_HEAD.size + length
                if length >= _CHUNK_MIN_BODY and end <= size:
                    with contextlib.suppress(Exception):  # most candidates are random bytes
                        if _intact_chunk(
                            Chunk.read(_BoundedStream(BytesIO(data[at + _RECORD_HEAD.size : end])))
                        ):
                            return at
            at = data.find(bytes([Opcode.CHUNK]), at + 1)
    return None


def _intact_chunk(chunk: Chunk) -> bool:
    """Whether ``chunk`` has a non-zero CRC matching its decompressed records (and they parse)."""
    if chunk.uncompressed_crc == 0:
        return False  # no CRC: nothing tells a real chunk from bytes that happen to parse
    try:
        _chunk_records(chunk)
    except Exception:  # noqa: BLE001 -- damaged bytes make any error possible
        return False
    return True


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
