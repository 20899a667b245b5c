"""Damaged bags: every reader turns damage into one BagError naming the bag and the file; `recover_bag`
restores every complete message of a truncated or unfinished bag (whatever the cut), keeps custom_data,
leaves no temporary file and refuses a bag whose writer is still alive."""

from __future__ import annotations

import contextlib
import io
import re
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader as RosbagsReader

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import DEFAULT_CAMERA
from playseg_ros.bag import BagError, BagReader, BagWriter, recover_bag, topic_info
from playseg_ros.bag.lock import LOCK_FILE
from playseg_ros.bag.recovery import LOSS_KEY
from playseg_ros.cli import main as cli_main
from playseg_ros.play_bags import DataInfo, iter_play_bag, read_play_bag, write_play_bag
from playseg_ros.typestore import playseg_typestore

ROOT = Path(__file__).resolve().parent.parent
SAMPLE_PLAY = ROOT / "bags" / "play"
CUSTOM = {"playseg.domain": "test", "note": "kept through recovery"}
STRING = "std_msgs/msg/String"


def _episode(index: int, num_steps: int = 10) -> Episode:
    rng = np.random.default_rng(index)
    return Episode(
        episode_id=f"ep-{index:03d}",
        images={DEFAULT_CAMERA: rng.integers(0, 256, (num_steps + 1, 12, 12, 3), dtype=np.uint8)},
        actions=rng.integers(0, 7, (num_steps, 1)).astype(np.float32),
        segments=[Segment(0, 4, "go to the red ball"), Segment(4, num_steps, "go to a blue key")],
    )


@pytest.fixture(scope="module")
def play_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small play bag of 12 episodes in many small chunks, declaring a domain in custom_data."""
    path = tmp_path_factory.mktemp("bags") / "play"
    write_play_bag(
        path, [_episode(i) for i in range(12)], annotated=True, info=DataInfo(domain="test"), chunk_bytes=4000
    )
    return path


def _copy(bag: Path, to: Path) -> tuple[Path, Path]:
    shutil.copytree(bag, to)
    return to, next(to.glob("*.mcap"))


def _chunk_offsets(file: Path) -> list[int]:
    with file.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return sorted(index.chunk_start_offset for index in summary.chunk_indexes)


# --- damage, each reader -------------------------------------------------------------------------------


def _garbage_in_the_middle(file: Path) -> None:
    """2 KB of deterministic garbage over the middle of the file (inside some chunk)."""
    data = bytearray(file.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 2048] = np.random.default_rng(7).integers(0, 256, 2048, dtype=np.uint8).tobytes()
    file.write_bytes(data)


def _cut_at_two_thirds(file: Path) -> None:
    file.write_bytes(file.read_bytes()[: file.stat().st_size * 2 // 3])


def _emptied(file: Path) -> None:
    file.write_bytes(b"")


def _index_pointing_elsewhere(file: Path) -> None:
    """The summary's chunk index of a middle chunk points at the wrong offset (the records are intact)."""
    data = bytearray(file.read_bytes())
    offsets = _chunk_offsets(file)
    target = offsets[len(offsets) // 2]
    at = data.rindex(struct.pack("<Q", target))  # the last occurrence is in the chunk index
    data[at : at + 8] = struct.pack("<Q", offsets[0] + 5)
    file.write_bytes(data)


def _removed(file: Path) -> None:
    file.unlink()


def _all_messages(bag: Path) -> None:
    with BagReader(bag) as reader:
        for _ in reader.messages():
            pass


def _play_episodes(bag: Path) -> None:
    read_play_bag(bag)


def _streamed_episodes(bag: Path) -> None:
    for _ in iter_play_bag(bag, truth=True):
        pass


def _bag_info_cli(bag: Path) -> None:
    """`playseg bag info`: exit 1 and its one-line message, raised here as the BagError it printed."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = cli_main(["bag", "info", str(bag)])
    if code != 0:
        raise BagError(bag, err.getvalue().strip())


TRUNCATED = r"the file is truncated or unfinished \(no MCAP footer .*`playseg bag recover` restores"
DAMAGES: list[tuple[str, Callable[[Path], None], str]] = [
    (
        "garbage in a chunk",
        _garbage_in_the_middle,
        r"damaged chunk record at byte \d+: .*after \d+ good messages",
    ),
    ("cut short", _cut_at_two_thirds, TRUNCATED),
    ("emptied", _emptied, TRUNCATED),
    ("index pointing elsewhere", _index_pointing_elsewhere, r"cannot read: .*after \d+ good messages"),
    ("file missing", _removed, r"file is missing"),
]
READERS: list[tuple[str, Callable[[Path], None]]] = [
    ("BagReader.messages", _all_messages),
    ("read_play_bag", _play_episodes),
    ("iter_play_bag", _streamed_episodes),
    ("bag info", _bag_info_cli),
]


@pytest.mark.parametrize(("damage", "spoil", "detail"), DAMAGES, ids=[d[0] for d in DAMAGES])
@pytest.mark.parametrize(("reader", "read"), READERS, ids=[r[0] for r in READERS])
def test_a_damaged_file_is_one_bag_error_naming_bag_and_file(
    tmp_path: Path, play_bag: Path, damage: str, spoil, detail: str, reader: str, read
) -> None:
    bag, file = _copy(play_bag, tmp_path / "play")
    spoil(file)
    if reader == "bag info" and damage in ("garbage in a chunk", "index pointing elsewhere"):
        read(bag)  # info reads the metadata and the summary, not the chunks: nothing to see
        return
    with pytest.raises(BagError) as caught:
        read(bag)
    message = str(caught.value)
    assert "\n" not in message
    assert f"bag '{bag}'" in message and f"file '{file.name}'" in message, message
    assert re.search(detail, message), message


# --- recovery of truncated bags -------------------------------------------------------------------------


def _rosbags_count(bag: Path) -> int:
    with RosbagsReader(bag) as reader:
        return sum(1 for _ in reader.messages())


def _leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.parent.rglob("*") if p.name.endswith((".recovered", LOCK_FILE)))


def test_a_truncated_sample_bag_with_metadata_is_recovered_in_place(tmp_path: Path) -> None:
    """The issue's case: bags/play cut short, metadata.yaml left behind."""
    bag, file = _copy(SAMPLE_PLAY, tmp_path / "play")
    with BagReader(SAMPLE_PLAY) as reader:
        custom, total = reader.custom_data, reader.message_count
    _cut_at_two_thirds(file)
    with pytest.raises(BagError, match=TRUNCATED):
        BagReader(bag)

    (report,) = recover_bag(bag)
    assert report.rebuilt and 0 < report.messages < total and report.dropped_bytes > 0
    assert _rosbags_count(bag) == report.messages
    assert report.lossy and report.lost_messages == total - report.messages  # metadata counted them
    with BagReader(bag) as reader:
        notes = dict(reader.custom_data)
        assert f"{total - report.messages} messages lost" in notes.pop(LOSS_KEY)
        assert notes == custom  # the feature schema survives
        assert reader.message_count == report.messages
    episodes = read_play_bag(bag, incomplete="drop")
    assert 0 < len(episodes) < 80
    assert _leftovers(bag) == []
    with pytest.raises(BagError, match="nothing to recover"):
        recover_bag(bag)


def _string_bag(path: Path, count: int, **options) -> None:
    """``count`` std_msgs/String messages 'NNNN ...' on two topics, in small chunks, with CUSTOM."""
    store = playseg_typestore()
    writer = BagWriter(path, custom_data=CUSTOM, chunk_bytes=600, **options)
    writer.add_topic(topic_info("/a", STRING))
    writer.add_topic(topic_info("/b", STRING))
    for i in range(count):
        msg = store.types[STRING](data=f"{i:04d} " + "z" * 90)
        writer.write("/a" if i % 3 else "/b", store.serialize_cdr(msg, STRING), 1000 + i)
    writer.close()


def _texts(bag: Path) -> list[str]:
    store = playseg_typestore()
    with RosbagsReader(bag) as reader:
        return [store.deserialize_cdr(raw, STRING).data[:4] for _, _, raw in reader.messages()]


def _as_partial(bag: Path) -> Path:
    """The finished bag turned back into what a writer killed after its last write leaves."""
    partial = bag.with_name(bag.name + ".partial")
    bag.rename(partial)
    (partial / "metadata.yaml").unlink()
    return partial


@pytest.mark.parametrize(
    "case", ["partial, one file cut", "no metadata.yaml, one file cut", "partial, second split file cut"]
)
def test_a_truncated_bag_without_metadata_is_recovered_with_its_custom_data(
    tmp_path: Path, case: str
) -> None:
    bag = tmp_path / "rec"
    split = "split" in case
    _string_bag(bag, 200, max_file_bytes=6000 if split else 0)
    files = sorted(bag.glob("*.mcap"))
    assert (len(files) >= 2) if split else (len(files) == 1)
    cut = max(files, key=lambda f: int(f.stem.rsplit("_", 1)[1]))
    chunks = _chunk_offsets(cut)
    cut.write_bytes(cut.read_bytes()[: chunks[len(chunks) // 2] + 20])  # inside a chunk
    if case.startswith("partial"):
        _as_partial(bag)
    else:
        (bag / "metadata.yaml").unlink()

    report = recover_bag(bag)
    assert [r.path for r in report if r.rebuilt] == [cut.name] and len(report) == len(files)
    kept = sum(r.messages for r in report)
    assert 0 < kept < 200
    assert _texts(bag) == [f"{i:04d}" for i in range(kept)]  # every message before the cut, in order
    with BagReader(bag) as reader:
        assert reader.custom_data == CUSTOM
    assert _leftovers(bag) == [] and not bag.with_name("rec.partial").exists()
    (bag / "metadata.yaml").unlink()  # lost again: the rebuilt file itself carries custom_data now
    assert sum(r.messages for r in recover_bag(bag)) == kept
    with BagReader(bag) as reader:
        assert reader.custom_data == CUSTOM


@pytest.mark.slow
def test_recovery_never_fails_at_any_truncation_offset(tmp_path: Path) -> None:
    """Cut a file at 50 offsets spread over it (and inside its first records): recovery always succeeds,
    rosbags reads the result, and the longer the file, the more messages come back (all of them uncut)."""
    source = tmp_path / "src"
    _string_bag(source, 120)
    data = (source / "src_0.mcap").read_bytes()
    offsets = sorted({*range(0, 60, 7), *np.linspace(60, len(data), 50).astype(int).tolist()})
    previous = -1
    for offset in offsets:
        partial = tmp_path / f"cut{offset}.partial"
        partial.mkdir()
        (partial / f"cut{offset}_0.mcap").write_bytes(data[:offset])
        bag = tmp_path / f"cut{offset}"
        (report,) = recover_bag(bag)
        texts = _texts(bag)
        assert len(texts) == report.messages >= previous, offset
        assert texts == [f"{i:04d}" for i in range(len(texts))], offset
        previous = len(texts)
        with BagReader(bag) as reader:
            assert reader.custom_data in ({}, CUSTOM), offset  # {} only when cut inside the first records
        shutil.rmtree(bag)
    assert previous == 120
    assert _leftovers(tmp_path / "src") == []


# --- locking and failures -------------------------------------------------------------------------------

_WRITER_CHILD = textwrap.dedent(
    """
    import sys, time
    from playseg_ros.bag import BagWriter, topic_info
    from playseg_ros.typestore import playseg_typestore

    store = playseg_typestore()
    writer = BagWriter(sys.argv[1], chunk_bytes=1)
    writer.add_topic(topic_info("/a", "std_msgs/msg/String"))
    for i in range(int(sys.argv[2])):
        msg = store.types["std_msgs/msg/String"](data=f"{i:04d}")
        writer.write("/a", store.serialize_cdr(msg, "std_msgs/msg/String"), 1000 + i)
    print("written", flush=True)
    time.sleep(60)
    """
)


def test_recover_refuses_a_bag_being_written_until_its_writer_is_gone(tmp_path: Path) -> None:
    bag = tmp_path / "live"
    child = subprocess.Popen(
        [sys.executable, "-c", _WRITER_CHILD, str(bag), "25"], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline().strip() == "written"
        with pytest.raises(BagError, match=rf"bag '{bag}': is still being written by process {child.pid} "):
            recover_bag(bag)
        with pytest.raises(FileExistsError, match=rf"being written by process {child.pid}"):
            BagWriter(bag)
        assert sorted(p.name for p in (tmp_path / "live.partial").iterdir()) == [LOCK_FILE, "live_0.mcap"]
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
    (report,) = recover_bag(bag)  # the kernel released the killed writer's lock
    assert report.messages == 25 and _rosbags_count(bag) == 25
    assert _leftovers(bag) == []


_FULL_DISK_CHILD = textwrap.dedent(
    """
    import resource, sys
    from playseg_ros.bag import BagError, BagWriter, recover_bag, topic_info
    from playseg_ros.typestore import playseg_typestore

    # Files may not grow past this size (Python ignores SIGXFSZ, so a write fails with EFBIG): a full disk.
    limit = int(sys.argv[3])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
    if sys.argv[1] == "record":
        store = playseg_typestore()
        writer = BagWriter(sys.argv[2], chunk_bytes=1 << 20)
        writer.add_topic(topic_info("/a", "std_msgs/msg/String"))
        flushed = 0
        try:
            for i in range(100000):
                msg = store.types["std_msgs/msg/String"](data=f"{i:04d} " + "q" * 200)
                writer.write("/a", store.serialize_cdr(msg, "std_msgs/msg/String"), 1000 + i)
                if i % 10 == 9:
                    writer.flush()
                    flushed = i + 1
        except OSError as error:
            writer.abandon()
            print(f"flushed {flushed} then {error.strerror}", flush=True)
    else:
        try:
            recover_bag(sys.argv[2])
        except BagError as error:
            print(error, flush=True)
    """
)


def test_a_bag_whose_disk_filled_up_recovers_and_a_full_disk_during_recovery_changes_nothing(
    tmp_path: Path,
) -> None:
    bag = tmp_path / "full"

    def child(mode: str, limit: int) -> str:
        result = subprocess.run(
            [sys.executable, "-c", _FULL_DISK_CHILD, mode, str(bag), str(limit)],
            cwd=ROOT, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        return result.stdout.strip()

    said = child("record", 40_000)  # the .mcap file stops growing mid-chunk at 40 kB
    assert said.endswith("File too large"), said
    flushed = int(said.split()[1])
    partial = tmp_path / "full.partial"
    before = {p.name: p.read_bytes() for p in partial.iterdir()}
    assert list(before) == ["full_0.mcap"] and len(before["full_0.mcap"]) == 40_000

    said = child("recover", 1_000)  # the rebuilt file cannot be written either
    assert "file 'full_0.mcap': cannot write the recovered file" in said and "File too large" in said, said
    assert {p.name: p.read_bytes() for p in partial.iterdir()} == before  # untouched, no .recovered left

    (report,) = recover_bag(bag)
    assert report.messages >= flushed > 0
    assert _texts(bag) == [f"{i:04d}" for i in range(report.messages)]
    assert _leftovers(bag) == []


def test_a_writer_that_fails_keeps_what_it_flushed_for_recovery(tmp_path: Path) -> None:
    """The second split file lands on a full device: the first file stays finished and recoverable."""
    bag = tmp_path / "split"
    store = playseg_typestore()
    writer = BagWriter(bag, max_file_bytes=4000, chunk_bytes=500, custom_data=CUSTOM)
    (tmp_path / "split.partial" / "split_1.mcap").symlink_to("/dev/full")
    writer.add_topic(topic_info("/a", STRING))
    written = 0
    with pytest.raises(OSError, match="No space left"):
        for i in range(1000):
            msg = store.types[STRING](data=f"{i:04d} " + "w" * 100)
            writer.write("/a", store.serialize_cdr(msg, STRING), 1000 + i)
            written = i + 1
            writer.flush()
    writer.abandon()
    (tmp_path / "split.partial" / "split_1.mcap").unlink()  # space freed: the broken file is gone
    (report,) = recover_bag(bag)
    assert not report.rebuilt and 0 < report.messages < written
    assert _texts(bag) == [f"{i:04d}" for i in range(report.messages)]
    with BagReader(bag) as reader:
        assert reader.custom_data == CUSTOM


def test_recover_names_what_it_cannot_do(tmp_path: Path) -> None:
    _string_bag(tmp_path / "done", 10)
    with pytest.raises(BagError, match="already a finished bag .*nothing to recover"):
        recover_bag(tmp_path / "done")
    with pytest.raises(BagError, match="neither .* nor .* is a bag directory"):
        recover_bag(tmp_path / "nothing")
    shutil.copytree(tmp_path / "done", tmp_path / "done.partial")
    with pytest.raises(BagError, match="both .* exist"):
        recover_bag(tmp_path / "done")
    meta = yaml.safe_load((tmp_path / "done" / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["message_count"] = 3  # metadata that does not match the files
    (tmp_path / "done" / "metadata.yaml").write_text(yaml.safe_dump(meta))
    shutil.rmtree(tmp_path / "done.partial")
    report = recover_bag(tmp_path / "done")
    assert [(r.rebuilt, r.messages) for r in report] == [(False, 10)]
    with BagReader(tmp_path / "done") as reader:
        assert reader.message_count == 10 and reader.custom_data == CUSTOM


def test_recover_loses_nothing_past_damage_and_refuses_a_file_that_is_not_mcap(tmp_path: Path) -> None:
    bag, file = _copy(SAMPLE_PLAY, tmp_path / "damaged")
    _garbage_in_the_middle(file)
    _cut_at_two_thirds(file)  # unfinished, so rebuilt: the scan stops at the garbage, not at the cut
    original = file.read_bytes()
    (item,) = recover_bag(bag)
    assert item.rebuilt and item.messages > 0 and item.kept_original == file.name + ".damaged"
    assert (bag / item.kept_original).read_bytes() == original  # what lies past the garbage is kept
    assert _rosbags_count(bag) == item.messages  # and the rebuilt file alone is the bag

    bag, file = _copy(SAMPLE_PLAY, tmp_path / "not-mcap")
    data = bytearray(file.read_bytes())
    data[1] = ord("X")  # one byte of the magic
    file.write_bytes(data)
    metadata = (bag / "metadata.yaml").read_bytes()
    with pytest.raises(BagError, match=f"file '{file.name}'.*not an MCAP file .*left as it is"):
        recover_bag(bag)
    assert file.read_bytes() == bytes(data) and (bag / "metadata.yaml").read_bytes() == metadata
    assert _leftovers(bag) == []


@pytest.mark.parametrize(
    ("metadata", "detail"),
    [
        (None, "no such bag directory"),
        ("", "holds no rosbag2_bagfile_information mapping"),
        ("a: 1\n", "holds no rosbag2_bagfile_information mapping"),
        ("rosbag2_bagfile_information: {}\n", "cannot read metadata.yaml: KeyError"),
    ],
)
def test_a_missing_bag_or_metadata_without_its_mapping_is_named(
    tmp_path: Path, metadata: str | None, detail: str
) -> None:
    bag = tmp_path / "bag"
    if metadata is not None:
        bag, _ = _copy(SAMPLE_PLAY, bag)
        (bag / "metadata.yaml").write_text(metadata)
    with pytest.raises(BagError) as caught:
        BagReader(bag)
    assert f"bag '{bag}'" in str(caught.value) and detail in str(caught.value), caught.value


def test_a_bag_whose_recording_did_not_finish_points_at_recovery(tmp_path: Path) -> None:
    (tmp_path / "bag.partial").mkdir()
    with pytest.raises(BagError, match=r"no metadata.yaml \(an unfinished recording is at .*bag recover"):
        BagReader(tmp_path / "bag")
