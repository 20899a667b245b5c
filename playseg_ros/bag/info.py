"""`playseg bag info`: a human-readable description of a bag."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader

from playseg_ros.bag.errors import BagError
from playseg_ros.bag.reader import BagReader
from playseg_ros.bag.recovery import LOSS_KEY


def bag_info_text(path: Path | str) -> str:
    """A human-readable description of a bag (for ``playseg bag info``)."""
    with BagReader(path) as reader:
        meta = reader.metadata
        lines = [
            f"bag:        {reader.path}",
            f"storage:    {meta['storage_identifier']} (metadata version {meta['version']}, "
            f"ros_distro {meta.get('ros_distro', '?')})",
            f"start:      {meta['starting_time']['nanoseconds_since_epoch'] / 1e9:.3f} s since epoch",
            f"duration:   {meta['duration']['nanoseconds'] / 1e9:.3f} s",
            f"messages:   {meta['message_count']}",
        ]
        note = (meta.get("custom_data") or {}).get(LOSS_KEY)
        if note:  # a recovery could not keep everything: said as long as this metadata.yaml stands
            lines.append(f"LOSSES:     {note}")
        lines.append("files:")
        for file in reader.files:
            size = file.stat().st_size if file.exists() else 0
            lines.append(f"  {file.name}  {size / 1e6:.2f} MB{_chunk_compression(reader.path, file)}")
        lines.append("topics:")
        for entry in meta["topics_with_message_count"]:
            topic = entry["topic_metadata"]
            lines.append(f"  {topic['name']}  {topic['type']}  {entry['message_count']} messages")
    return "\n".join(lines)


def _chunk_compression(bag: Path, file: Path) -> str:
    if file.suffix != ".mcap":
        return ""
    try:
        with file.open("rb") as stream:
            summary = make_reader(stream).get_summary()
    except Exception as error:  # noqa: BLE001 -- a damaged summary can make the mcap reader raise anything
        raise BagError(
            bag, f"cannot read its summary: {type(error).__name__}: {error}", file=file.name
        ) from None
    if summary is None:
        return ""
    kinds = sorted({index.compression or "none" for index in summary.chunk_indexes})
    return f", {len(summary.chunk_indexes)} chunks, compression {'/'.join(kinds) or 'none'}"
