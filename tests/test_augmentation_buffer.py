"""The trainer's augmentation buffer keeps every acknowledged segment across crashes."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from playseg_core.augment.buffer import AugmentationBuffer
from playseg_core.data.episode import Segment, SegmentClip

CAMERA = "observation.images.top"


def _segment(i: int) -> SegmentClip:
    rng = np.random.default_rng(i)
    length = 2 + i % 5
    instruction = f"go to the red {('ball', 'box', 'key')[i % 3]}"
    return SegmentClip(
        episode_id=f"ep{i // 3}",
        segment=Segment(i, i + length, instruction, confidence=0.5 + i / 100, log_prob=-i / 10),
        actions=rng.integers(0, 7, (length, 1)).astype(np.float32),
        state=rng.integers(0, 11, (length + 1, 8, 8, 3)).astype(np.uint8),
        images={CAMERA: rng.integers(0, 256, (length + 1, 4, 4, 3)).astype(np.uint8)} if i % 2 else {},
        source="test",
    )


def _assert_same(a: SegmentClip, b: SegmentClip) -> None:
    assert (a.episode_id, a.source) == (b.episode_id, b.source)
    assert a.segment == b.segment  # confidence and log_prob are stored as float64: exact
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.state, b.state)
    assert a.images.keys() == b.images.keys()
    for camera in a.images:
        np.testing.assert_array_equal(a.images[camera], b.images[camera])


def test_roundtrip_and_reopen(tmp_path):
    with AugmentationBuffer(tmp_path / "buf") as buf:
        for i in range(7):
            assert buf.append(_segment(i)) == i
        assert len(buf) == 7
        _assert_same(buf[3], _segment(3))
    reopened = AugmentationBuffer(tmp_path / "buf")
    assert len(reopened) == 7
    assert reopened.num_steps == sum(_segment(i).segment.length for i in range(7))
    for i, seg in enumerate(reopened):
        _assert_same(seg, _segment(i))
    reopened.append(_segment(7))
    assert len(AugmentationBuffer(tmp_path / "buf")) == 8


def test_torn_tail_is_cut_and_acknowledged_segments_survive(tmp_path):
    log = tmp_path / "segments.log"
    with AugmentationBuffer(tmp_path) as buf:
        for i in range(4):
            buf.append(_segment(i))
        four = log.stat().st_size
        buf.append(_segment(4))
    five = log.stat().st_size
    with open(log, "r+b") as f:  # a crash in the middle of the fifth append
        f.truncate(four + (five - four) // 2)
    buf = AugmentationBuffer(tmp_path)
    assert len(buf) == 4
    assert buf.recovered_bytes == (five - four) // 2
    assert log.stat().st_size == four
    _assert_same(buf[3], _segment(3))


def test_corruption_in_the_middle_is_an_error_naming_the_file(tmp_path):
    with AugmentationBuffer(tmp_path) as buf:
        for i in range(3):
            buf.append(_segment(i))
    log = tmp_path / "segments.log"
    data = bytearray(log.read_bytes())
    data[60] ^= 0xFF
    log.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="segments.log"):
        AugmentationBuffer(tmp_path)


def test_sigkill_after_acknowledgement_loses_nothing(tmp_path):
    # A writer process appends and prints each acknowledged index; we kill it hard mid-stream.
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(tmp_path.parent)!r})
        from tests_buffer_peer import run
        run({str(tmp_path / "buf")!r})
        """
    )
    peer = tmp_path.parent / "tests_buffer_peer.py"
    peer.write_text(
        textwrap.dedent(
            """
            import numpy as np
            from playseg_core.augment.buffer import AugmentationBuffer
            from playseg_core.data.episode import Segment, SegmentClip
            def run(path):
                buf = AugmentationBuffer(path)
                for i in range(100000):
                    a = np.full((3, 1), i % 7, np.float32)
                    buf.append(SegmentClip(f"ep{i}", Segment(0, 3, "go to the red ball"), a,
                                           state=np.zeros((4, 8, 8, 3), np.uint8)))
                    print(i, flush=True)
            """
        )
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    acknowledged = -1
    for line in proc.stdout:
        acknowledged = int(line)
        if acknowledged >= 30:
            break
    proc.kill()
    proc.wait()
    buf = AugmentationBuffer(tmp_path / "buf")
    assert len(buf) >= acknowledged + 1
    assert [int(s.actions[0, 0]) for s in buf] == [i % 7 for i in range(len(buf))]
