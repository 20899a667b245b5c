"""Hostile and mistaken input: every YAML the project reads goes through one bounded loader
(playseg_core/yaml_io.py), and each bad file, value, path or argument is one line naming the file, entry,
bag or option, exit non-zero, never a hang or a traceback; a bad bag in a multi-bag run fails alone."""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from mcap.records import Chunk
from test_convert import MAPPING, RobotBag, write_mapping, write_rosbag2

from playseg_core.data.dataset import PlayDataset
from playseg_core.yaml_io import YamlFileError, YamlLimits, load_yaml
from playseg_ros.bag.errors import BagError
from playseg_ros.bag.mcap_scan import RecordScan
from playseg_ros.bag.reader import BagReader
from playseg_ros.cli import main
from playseg_ros.convert import MappingError, convert, load_mapping
from playseg_ros.launch import load_graph

# 9 levels of 9 aliases each: 9^9 (387 million) strings from 342 bytes
BILLION_LAUGHS = '\n'.join(
    ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    + [f"a{k}: &a{k} [{','.join([f'*a{k - 1}'] * 9)}]" for k in range(1, 9)]
) + "\n"  # fmt: skip
SECRET = "hunter2-s3cr3t"


def one_line_error(capsys: pytest.CaptureFixture[str]) -> list[str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return err.strip().splitlines()


# -- the loader ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "key", "detail"),
    [
        (BILLION_LAUGHS, "a6", "its aliases expand to more than 2000000 values (line 7)"),
        ("a: " + "[" * 5000 + "]" * 5000 + "\n", None, "nested deeper than 64 levels (line 1)"),
        ("a: &x [1, *x]\n", "a[1]", "an alias refers to a node that contains it"),
        ("base: &b {x: 1, y: 2, x: 3}\nother: *b\n", "base.x", "given twice (lines 1 and 1)"),
        ("a: 1\nb:\n  c: 2\n  c: 3\n", "b.c", "given twice (lines 3 and 4)"),
        (f"a: !!python/object/apply:os.system ['{SECRET}']\n", None, "could not determine a constructor"),
        (f"key: [{SECRET}\n", None, "not valid YAML (line 2, column 1)"),
        (f"a: 2024-13-45\nb: {SECRET}\n", None, "a value cannot be read: month must be in 1..12"),
        ("n: 1" + "0" * 5000 + "\n", None, "a whole number of more than 4300 digits"),
        (f"a: {SECRET}\x00\n", None, "character U+0000 at offset"),
    ],
)  # fmt: skip
def test_the_loader_refuses_bombs_depth_cycles_duplicates_and_bad_text_in_one_line(
    tmp_path: Path, text: str, key: str | None, detail: str
) -> None:
    path = tmp_path / "file.yaml"
    path.write_text(text)
    with pytest.raises(YamlFileError) as caught:  # refused by a limit, before any expansion
        load_yaml(path, "mapping")
    message = str(caught.value)
    assert "\n" not in message and message.startswith(f"mapping {str(path)!r}"), message
    assert detail in message and caught.value.key == key, message
    assert SECRET not in message  # nothing of a file that did not parse is quoted


def test_the_loader_limits_size_names_binary_files_and_directories(tmp_path: Path) -> None:
    path = tmp_path / "big.yaml"
    path.write_text("a: " + "x" * 200 + "\n")
    with pytest.raises(YamlFileError, match=r"larger than 100 bytes; refusing to read it"):
        load_yaml(path, limits=YamlLimits(max_bytes=100))
    assert load_yaml(path, limits=YamlLimits(max_bytes=1000)) == {"a": "x" * 200}
    binary = tmp_path / "map.bin"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)))
    with pytest.raises(YamlFileError) as caught:
        load_yaml(binary, "mapping")
    assert str(caught.value) == (
        f"mapping {str(binary)!r}: not UTF-8 text (byte 0x89 at offset 0): a binary file?"
    )
    with pytest.raises(YamlFileError, match=r"is a directory, not a file"):
        load_yaml(tmp_path)
    # what real files use stays: anchors, merge keys, JSON
    text = "base: &b {x: 1}\nmerged: {<<: *b, y: 2}\nlist: [*b, *b]\n"
    (tmp_path / "ok.yaml").write_text(text)
    assert load_yaml(tmp_path / "ok.yaml") == {
        "base": {"x": 1}, "merged": {"x": 1, "y": 2}, "list": [{"x": 1}, {"x": 1}]
    }  # fmt: skip


def test_a_billion_laughs_mapping_fails_convert_at_once_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=0.5))
    (tmp_path / "bomb.yaml").write_text(BILLION_LAUGHS)
    argv = ["convert", str(bag), "--out", str(tmp_path / "out"), "--mapping", str(tmp_path / "bomb.yaml")]
    assert main(argv) == 1  # the expansion limit, not the expansion, ends it
    assert one_line_error(capsys) == [
        f"playseg convert: mapping {str(tmp_path / 'bomb.yaml')!r}, key 'a6': its aliases expand to more "
        "than 2000000 values (line 7); refusing it (an alias bomb?)"
    ]
    assert not (tmp_path / "out").exists()


def test_metadata_yaml_and_graph_configs_go_through_the_loader(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=0.5))
    (bag / "metadata.yaml").write_text(BILLION_LAUGHS)
    with pytest.raises(BagError) as caught:
        BagReader(bag)
    assert str(caught.value).startswith(f"bag '{bag}': cannot read metadata.yaml, key 'a6': its aliases")
    summary = convert(
        [bag], tmp_path / "out", load_mapping(write_mapping(tmp_path / "m.yaml")), progress=False
    )
    (failed,) = summary.failed
    assert "metadata.yaml" in failed.error and "alias bomb" in failed.error, failed.error
    config = tmp_path / "graph.yaml"
    config.write_text(BILLION_LAUGHS)
    with pytest.raises(ValueError, match=rf"graph config '{config}', key 'a6': its aliases expand"):
        load_graph(config)


# -- sidecars ----------------------------------------------------------------------------------------


def test_a_sidecar_with_non_finite_or_huge_times_fails_its_bag_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bags = tmp_path / "bags"
    times = {"a_good": "0.9", "b_inf": ".inf", "c_nan": ".nan", "d_huge": "1.0e+300", "e_good": "0.8"}
    for name, end in times.items():
        bag = write_rosbag2(bags / name, RobotBag(seconds=1.0, labels=[]))
        (bag / "labels.yaml").write_text(f"annotations:\n  - {{start: 0.0, end: 0.5, instruction: a}}\n"
                                         f"  - {{start: 0.6, end: {end}, instruction: b}}\n")  # fmt: skip
    mapping = write_mapping(tmp_path / "m.yaml", dict(MAPPING, annotations={"file": "labels.yaml"}))
    out = tmp_path / "out"
    assert main(["convert", str(bags), "--out", str(out), "--mapping", str(mapping), "--quiet"]) == 1
    lines = one_line_error(capsys)
    failed = sorted(line for line in lines if "failed:" in line)
    assert failed == [
        f"playseg convert: failed: bag '{bags / name}': annotations file '{bags / name / 'labels.yaml'}', "
        "annotations[1], key 'end': must be a finite number of seconds within +-4e+09"
        for name in ("b_inf", "c_nan", "d_huge")
    ]
    # the file each converted bag's labels came from is named
    assert f"a_good: 2 label(s) from annotations file '{bags / 'a_good' / 'labels.yaml'}'" in lines
    dataset = PlayDataset.open(out)
    assert sorted(Path(r.extra["bag"]).name for r in dataset.records) == ["a_good", "e_good"]
    assert not (tmp_path / ".out.convert").exists()


@pytest.mark.slow
def test_an_unrelated_file_as_sidecar_is_named_but_never_quoted(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=1.0, labels=[]))
    mapping = load_mapping(
        write_mapping(tmp_path / "m.yaml", dict(MAPPING, annotations={"file": str(tmp_path / "other")}))
    )
    shapes = {
        "passwd": f"root:x:0:0:{SECRET}:/root:/bin/bash\ndaemon:x:1:1:{SECRET}\n",  # one plain string
        "list": f"- {SECRET}\n- {SECRET}\n",
        "mapping": f"{SECRET}: 1\ntimes: absolute\n",
        "entry keys": f"- {{start: 1, end: 2, {SECRET}: 3}}\n",
        "values": f"- {{start: {SECRET}, end: 2, instruction: x}}\n",
        "times": f"times: {SECRET}\n",
        "not yaml": f"[{SECRET}: {{\n",
        "instruction": f"- {{start: 1, end: 2, instruction: [{SECRET}]}}\n",
    }
    for shape, text in shapes.items():
        (tmp_path / "other").write_text(text)
        summary = convert([bag], tmp_path / f"out-{len(text)}", mapping, progress=False)
        (failed,) = summary.failed
        error = failed.error or ""
        assert f"annotations file '{tmp_path / 'other'}'" in error, (shape, error)
        assert "\n" not in error and (SECRET not in error or shape in ("mapping", "entry keys")), (
            shape,
            error,
        )


def test_a_sidecar_outside_the_bag_needs_an_absolute_path_or_the_option(tmp_path: Path) -> None:
    bags = tmp_path / "bags"
    bag = write_rosbag2(bags / "arm", RobotBag(seconds=1.0, labels=[]))
    other = bags / "other_bag"
    other.mkdir()
    (other / "labels.yaml").write_text("annotations: [{start: 0.1, end: 0.6, instruction: theirs}]\n")
    relative = dict(MAPPING, annotations={"file": "../other_bag/labels.yaml"})
    summary = convert([bag], tmp_path / "out1", load_mapping(write_mapping(tmp_path / "a.yaml", relative)),
                      progress=False)  # fmt: skip
    (failed,) = summary.failed
    assert failed.error == (
        f"bag '{bag}': annotations file '../other_bag/labels.yaml' lies outside the bag's directory "
        f"'{bag}': give an absolute path, or allow_outside_bag: true under the mapping's annotations"
    )
    allowed = dict(MAPPING, annotations={"file": "../other_bag/labels.yaml", "allow_outside_bag": True})
    absolute = dict(MAPPING, annotations={"file": str(other / "labels.yaml")})
    for name, raw in (("b.yaml", allowed), ("c.yaml", absolute)):
        out = tmp_path / f"out-{name}"
        summary = convert([bag], out, load_mapping(write_mapping(tmp_path / name, raw)), progress=False)
        assert summary.failed == []
        (report,) = summary.reports
        used = str(other / "labels.yaml") if raw is absolute else str(bag / "../other_bag/labels.yaml")
        assert f"1 label(s) from annotations file {used!r}" in report.notes
        assert [s.instruction for s in PlayDataset.open(out).segments(0)] == ["theirs"]
    with pytest.raises(MappingError, match="'annotations.allow_outside_bag': must be true or false"):
        load_mapping(write_mapping(tmp_path / "d.yaml", dict(MAPPING, annotations={"file": "x",
                                                                                   "allow_outside_bag": "yes"})))  # fmt: skip


# -- mappings ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "key", "detail"),
    [
        ({"fps": 1e300}, "fps", "must be a positive number from 0.001 to 1000, got 1e+300"),
        ({"fps": 10**400}, "fps", "must be a positive number from 0.001 to 1000, got 1000000"),
        ({"fps": 1e-300}, "fps", "must be a positive number from 0.001 to 1000"),
        ({"tolerance_ms": float("nan")}, "tolerance_ms", "must be a positive number up to 1e+12, got nan"),
        ({"primary": ["a", "list"]}, "primary", "['a', 'list'] is not one of the observation features"),
        ({"features": dict(MAPPING["features"], **{"observation.images.front": {
            "topic": "/camera/image_raw", "resize": {"width": 10**9, "height": 10}}})},
         "features.observation.images.front.resize", "needs whole width and height from 1 to 4096"),
        ({"features": dict(MAPPING["features"], action={"topic": "/cmd_vel", "fields": ["linear.x"],
                                                        "low": [float("-inf")]})},
         "features.action.low", "must be a list of finite numbers"),
        ({"episodes": {"split": "gap", "gap_s": 1e30}}, "episodes.gap_s", "must be a positive number up to 1e+09"),
    ],
)  # fmt: skip
def test_absurd_mapping_values_are_named_errors(tmp_path: Path, change: dict, key: str, detail: str) -> None:
    path = write_mapping(tmp_path / "m.yaml", dict(MAPPING, **change))
    with pytest.raises(MappingError) as caught:
        load_mapping(path)
    assert caught.value.key == key and detail in str(caught.value) and len(str(caught.value)) < 300, (
        caught.value
    )


def test_a_deeply_nested_mapping_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=0.5))
    (tmp_path / "deep.yaml").write_text("fps: " + "[" * 100_000 + "]" * 100_000 + "\n")
    argv = ["convert", str(bag), "--out", str(tmp_path / "out"), "--mapping", str(tmp_path / "deep.yaml")]
    assert main(argv) == 1
    assert one_line_error(capsys) == [
        f"playseg convert: mapping {str(tmp_path / 'deep.yaml')!r}: nested deeper than 64 levels (line 1)"
    ]


# -- bags, models, experiment ------------------------------------------------------------------------


def test_a_corrupt_record_length_in_a_rosbags_chunk_names_file_and_offset(tmp_path: Path) -> None:
    """rosbags reads a schema by its length (an OverflowError for a flipped high bit), mcap by its fields:
    the scan now checks every length inside a chunk, so the message says where."""
    bag = write_rosbag2(tmp_path / "bag", RobotBag(seconds=1.0))
    (mcap,) = bag.glob("*.mcap")
    data = bytearray(mcap.read_bytes())
    chunk = next(offset for offset, record in RecordScan(mcap) if isinstance(record, Chunk))
    body = chunk + 9  # opcode, length
    (compression,) = struct.unpack_from("<I", data, body + 28)
    first_record = body + 32 + compression + 8  # past start, end, size, crc, compression, records length
    data[first_record + 8] ^= 0x80  # the top byte of the first inner record's length
    mcap.write_bytes(data)
    summary = convert(
        [bag], tmp_path / "out", load_mapping(write_mapping(tmp_path / "m.yaml")), progress=False
    )
    (failed,) = summary.failed
    assert (failed.error or "").startswith(
        f"bag '{bag}': unreadable after 0 messages: file '{mcap.name}': damaged chunk record at byte "
        f"{chunk}: the record at byte 0 inside it claims "
    ), failed.error


def test_a_directory_as_model_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    play = Path(__file__).parent.parent / "bags" / "play"
    argv = ["segment", "--model", str(tmp_path), "--input", str(play), "--out", str(tmp_path / "out")]
    assert main(argv) == 1
    assert one_line_error(capsys) == [
        f"playseg segment: checkpoint {tmp_path}: is a directory, not a checkpoint file"
    ]


def test_experiment_refuses_a_foreign_non_empty_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "elsewhere"
    (out / "models").mkdir(parents=True)
    (out / "models" / "ps.pt").write_bytes(b"not ours")
    assert main(["experiment", "babyai", "--scale", "tiny", "--out", str(out)]) == 1
    lines = one_line_error(capsys)
    assert lines == [
        f"playseg experiment: --out {out}: a non-empty directory that holds no experiment (no "
        "experiment.json); give a new or empty directory"
    ]
    assert "--overwrite" not in lines[0]
    assert sorted(p.name for p in out.rglob("*")) == ["models", "ps.pt"]  # nothing written, nothing read


# -- node processes ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("ros_args", "line"),
    [
        (["-p", "compression:=lz4"], r"\[ERROR\] \[\d+\.\d+\] \[recorder\]: recorder: invalid parameter: "
                                     r"compression: zstd \| none"),
        (["-r", "__node:=../evil"], r"error: invalid node name '\.\./evil' in '-r __node:=\.\./evil': a ROS "
                                    r"node name is letters, digits and '_'"),
    ],
)  # fmt: skip
@pytest.mark.slow
def test_a_lifecycle_node_with_a_bad_parameter_or_name_exits_2_with_one_line(
    tmp_path: Path, ros_args: list[str], line: str
) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "playseg_ros.nodes.recorder", "--ros-args", "-p", f"output:={tmp_path / 'bag'}",
         *ros_args],
        env=dict(os.environ), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and re.fullmatch(line, lines[0]), result.stderr
    assert not (tmp_path / "bag").exists() and not (tmp_path / "bag.partial").exists()


def test_safe_dump_round_trip_of_the_shipped_configs_still_loads(tmp_path: Path) -> None:
    """Every YAML shipped in the repository loads through the bounded loader unchanged."""
    root = Path(__file__).parent.parent
    files = [
        *root.glob("config/*.yaml"),
        *root.glob("bags/**/metadata.yaml"),
        *root.glob("bags/**/*map*.yaml"),
    ]
    assert files
    for file in files:
        assert load_yaml(file) == yaml.safe_load(file.read_text()), file
