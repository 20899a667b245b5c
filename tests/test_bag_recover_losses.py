"""`bag recover` past damage and around lost files: a damaged record (a flipped bit in a chunk's length,
garbage) is skipped and every complete message outside it kept; a split file deleted from a bag is named
with the messages metadata.yaml counted in it; any loss beyond a crash's open chunk is reported, noted in
the new metadata.yaml (`bag info` prints it) and the damaged original and the old metadata.yaml are kept.
Fuzzed: random truncations, bit flips and deleted split files (tests/test_bag_damage.py: the named cases
of truncation and damage)."""

from __future__ import annotations

import contextlib
import io
import shutil
import struct
import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from mcap.records import Chunk, Message
from rosbags.rosbag2 import Reader as RosbagsReader

from playseg_ros.bag import BagReader, BagWriter, recover_bag, topic_info
from playseg_ros.bag.mcap_scan import RecordScan
from playseg_ros.bag.recovery import LOSS_KEY, ORIGINAL_METADATA
from playseg_ros.cli import main as cli_main
from playseg_ros.typestore import playseg_typestore

STRING = "std_msgs/msg/String"


def _string_bag(path: Path, count: int, max_file_bytes: int = 0) -> Path:
    """``count`` std_msgs/String messages 'NNNN zzz...' in small chunks (a few messages each)."""
    store = playseg_typestore()
    writer = BagWriter(path, chunk_bytes=600, max_file_bytes=max_file_bytes)
    writer.add_topic(topic_info("/a", STRING))
    for i in range(count):
        msg = store.types[STRING](data=f"{i:04d} " + "z" * 90)
        writer.write("/a", store.serialize_cdr(msg, STRING), 1000 + i)
    writer.close()
    return path


def _texts(bag: Path) -> list[int]:
    store = playseg_typestore()
    with RosbagsReader(bag) as reader:
        return [int(store.deserialize_cdr(raw, STRING).data[:4]) for _, _, raw in reader.messages()]


def _chunks(file: Path, upto: int | None = None) -> dict[int, tuple[int, list[int]]]:
    """Chunk offset -> (its end, the message numbers in it), for chunks ending at or before ``upto``."""
    store = playseg_typestore()
    out: dict[int, tuple[int, list[int]]] = {}
    data = file.read_bytes()
    for offset, record in RecordScan(file):
        if isinstance(record, Chunk):
            length = struct.unpack_from("<Q", data, offset + 1)[0]
            out[offset] = (offset + 9 + length, [])
        elif isinstance(record, Message) and offset in out:
            out[offset][1].append(int(store.deserialize_cdr(record.data, STRING).data[:4]))
    return {o: v for o, v in out.items() if upto is None or v[0] <= upto}


def _recover_cli(bag: Path) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main(["bag", "recover", str(bag)])
    return code, out.getvalue(), err.getvalue()


@pytest.mark.parametrize("where", ["length", "data"])
def test_a_flipped_bit_in_a_chunk_of_a_truncated_file_costs_that_chunk_at_most(
    tmp_path: Path, where: str
) -> None:
    """The issue's case: a truncated file with one bit of a chunk record's length flipped. Before: the
    damage was taken for the cut (940 of 2,939 messages kept), the original overwritten. A damaged length
    is repaired from the chunk's own sizes (nothing lost); a bit flipped in a chunk's data fails its CRC:
    that chunk is skipped, every other complete one kept."""
    bag = _string_bag(tmp_path / "rec", 600)
    (file,) = bag.glob("*.mcap")
    cut = file.stat().st_size * 9 // 10
    chunks = _chunks(file, upto=cut)
    offsets = sorted(chunks)
    hit = offsets[len(offsets) // 3]
    data = bytearray(file.read_bytes()[:cut])
    if where == "length":  # a high bit: the chunk seems to run past the end of the file, like a cut
        data[hit + 1 + 5] ^= 0x10
    else:
        data[chunks[hit][0] - 20] ^= 0x01
    file.write_bytes(bytes(data))
    expected = sorted(
        n for o, (_, numbers) in chunks.items() if where == "length" or o != hit for n in numbers
    )
    assert len(expected) > 0.8 * 600

    code, out, err = _recover_cli(bag)
    assert code == 0
    assert _texts(bag) == expected  # every complete message outside the damaged chunk, in order
    damaged = bag / (file.name + ".damaged")
    assert damaged.read_bytes() == bytes(data)  # the damaged original is kept beside the rebuilt file
    assert f"{file.name}: {len(expected)} messages (rebuilt" in out and "damaged in 1 place(s)" in out
    assert f"playseg: warning: {file.name}: {file.name} damaged (" in err and f"bytes {hit}-" in err
    assert ("read with the length its other fields give" in err) == (where == "length")
    with BagReader(bag) as reader:
        assert reader.message_count == len(expected)
        assert reader.custom_data[LOSS_KEY].startswith(f"bag recover: {file.name} damaged (")
    assert "LOSSES:" in _info(bag)


def _info(bag: Path) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["bag", "info", str(bag)]) == 0
    return out.getvalue()


def test_a_deleted_split_file_is_named_with_its_messages_and_the_old_metadata_kept(tmp_path: Path) -> None:
    """The issue's case: a split bag with one file deleted. Before: exit 0, nothing said, metadata.yaml
    rewritten without the file, and `bag info` called the bag healthy."""
    bag = _string_bag(tmp_path / "split", 300, max_file_bytes=6000)
    files = sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
    assert len(files) >= 3
    old = (bag / "metadata.yaml").read_text()
    counted = {
        Path(f["path"]).name: f["message_count"]
        for f in yaml.safe_load(old)["rosbag2_bagfile_information"]["files"]
    }
    gone = files[1]
    gone.unlink()

    code, out, err = _recover_cli(bag)
    assert code == 0
    line = f"{gone.name}: MISSING: listed in metadata.yaml ({counted[gone.name]} messages), not on disk"
    assert line in out
    assert f"playseg: warning: {gone.name}: {gone.name} missing, {counted[gone.name]} messages" in err
    assert (bag / ORIGINAL_METADATA).read_text() == old  # the metadata that listed the file is kept
    assert len(_texts(bag)) == 300 - counted[gone.name]
    info = _info(bag)
    assert f"LOSSES:     bag recover: {gone.name} missing, {counted[gone.name]} messages" in info
    # a later recovery (metadata.yaml lost again) keeps the note: the loss never becomes invisible
    (bag / "metadata.yaml").unlink()
    recover_bag(bag)
    with BagReader(bag) as reader:
        assert f"{gone.name} missing" in reader.custom_data[LOSS_KEY]


def test_a_crash_tail_alone_is_no_loss(tmp_path: Path) -> None:
    """A file cut inside a chunk with no metadata.yaml counting it (what a crash leaves) keeps its
    original nowhere and notes nothing."""
    bag = _string_bag(tmp_path / "cut", 200)
    (bag / "metadata.yaml").unlink()  # written when a bag is closed: a crash leaves none
    (file,) = bag.glob("*.mcap")
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    code, out, err = _recover_cli(bag)
    assert code == 0 and err == "" and "trailing bytes dropped" in out
    assert not (bag / (file.name + ".damaged")).exists() and not (bag / ORIGINAL_METADATA).exists()
    with BagReader(bag) as reader:
        assert LOSS_KEY not in reader.custom_data


def test_a_finished_file_cut_short_is_a_loss(tmp_path: Path) -> None:
    """A file that metadata.yaml counted, cut later (an interrupted copy): the messages it lost are
    reported, the old metadata kept, and the note stays in the new metadata."""
    bag = _string_bag(tmp_path / "copied", 200)
    old = (bag / "metadata.yaml").read_text()
    (file,) = bag.glob("*.mcap")
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    code, out, err = _recover_cli(bag)
    kept = len(_texts(bag))
    assert code == 0 and 0 < kept < 200
    assert f"{200 - kept} of the 200 messages metadata.yaml counted lost" in out
    assert f"playseg: warning: {file.name}: {file.name} cut short" in err
    assert (bag / ORIGINAL_METADATA).read_text() == old
    with BagReader(bag) as reader:
        assert f"{200 - kept} messages lost" in reader.custom_data[LOSS_KEY]


# --- fuzzed ----------------------------------------------------------------------------------------------

_SOURCE: dict[str, Path] = {}


def _source(split: bool) -> Path:
    """One bag per kind, written once for all examples (hypothesis runs many in one test)."""
    key = "split" if split else "single"
    if key not in _SOURCE:
        _SOURCE[key] = _string_bag(
            Path(tempfile.mkdtemp(prefix="fuzz-recover-")) / key, 240, max_file_bytes=8000 if split else 0
        )
    return _SOURCE[key]


@pytest.mark.fuzz
@given(
    cut=st.floats(0.0, 1.0),
    flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 7)), max_size=2),
    split=st.booleans(),
    delete=st.integers(-1, 5),
)
@pytest.mark.slow
def test_recovery_keeps_every_complete_message_outside_damage_and_reports_every_loss(
    cut: float, flips: list[tuple[float, int]], split: bool, delete: int
) -> None:
    """A bag (one file or split) with its last file cut anywhere, up to two bits of it flipped anywhere
    and maybe one split file deleted: recovery never fails, keeps every message of every chunk that is
    complete before the cut and untouched by a flip, keeps nothing it invents, and whenever it dropped
    more than a clean tail it says so (a loss with counts, the original kept)."""
    work = Path(tempfile.mkdtemp(prefix="fuzz-recover-case-"))
    try:
        bag = work / "bag"
        shutil.copytree(_source(split), bag)
        files = sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1]))
        removed = files.pop(delete % len(files)) if split and delete >= 0 and len(files) > 1 else None
        last = files[-1]
        size = last.stat().st_size
        end = min(size - 1, max(9, int(size * cut)))  # always cut: a whole file is nothing to recover
        chunks = _chunks(last, upto=end)
        data = bytearray(last.read_bytes()[:end])
        flipped = []
        for where, bit in flips:
            at = min(len(data) - 1, int(where * len(data)))
            data[at] ^= 1 << bit
            flipped.append(at)
        last.write_bytes(bytes(data))
        if removed is not None:
            removed.unlink()
        intact = {n for f in files[:-1] for _, numbers in _chunks(f).values() for n in numbers}
        intact |= {
            n
            for offset, (stop, numbers) in chunks.items()
            if not any(offset <= at < stop for at in flipped)
            for n in numbers
        }
        if any(at < 8 for at in flipped):  # the magic itself: refused, left as it is
            return
        report = recover_bag(bag)
        kept = _texts(bag)
        assert kept == sorted(kept) and len(set(kept)) == len(kept)  # in order, nothing twice
        items = {item.path: item for item in report}
        touched = items[last.name]
        # every complete message outside the damage, but those whose channel record the damage took:
        # counted, never silently
        assert len(intact - set(kept)) <= touched.untyped_messages
        assert set(kept) <= set(range(240))
        if removed is not None:
            assert items[removed.name].missing and items[removed.name].expected_messages
        # every message lost is accounted for: inside a damaged range that is reported, or in the
        # trailing bytes reported dropped
        tail = len(data) - touched.dropped_bytes
        for offset, (stop, numbers) in chunks.items():
            if set(numbers) - set(kept):
                assert touched.rebuilt and (touched.damage or stop > tail), (offset, touched)
        with BagReader(bag) as reader:
            # a note for anything but a crash's clean tail: the source bag is finished, so metadata.yaml
            # counted every message and any cut of it loses some
            noted = removed is not None or bool(touched.damage) or bool(touched.lost_messages)
            assert (LOSS_KEY in reader.custom_data) == noted
        if touched.damage:
            assert touched.kept_original and (bag / touched.kept_original).is_file()
    finally:
        shutil.rmtree(work, ignore_errors=True)
