# ruff: noqa: F811 (a test takes the imported fixture `bags` as an argument)
"""`playseg review`'s server without a browser: bad inputs (a dataset without images, an episode of
100,000 steps, a hand-edited labels file with an error, a model of other features, a port in use, requests
another site could send) and HTTP range requests on the cached video."""

from __future__ import annotations

import hashlib
import json
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_convert_segment import untrained_model
from test_review_times import bags  # noqa: F401 (the fixture: two robot bags and their mapping)

from playseg_core.data.dataset import DatasetWriter, PlayDataset
from playseg_core.data.episode import Episode, Segment
from playseg_ros.review.app import review_dir, start
from playseg_ros.review.server import ReviewServer

LONG = 100_000


def write_dataset(path: Path, steps: tuple[int, ...], images: bool) -> Path:
    rng = np.random.default_rng(0)
    with DatasetWriter(path, ["reach", "wave"]) as writer:
        for k, n in enumerate(steps):
            episode = Episode(
                f"run:{k}",
                rng.standard_normal((n, 2)).astype(np.float32),
                images={"observation.images.top": moving_square(n + 1)} if images else {},
                state=rng.standard_normal((n + 1, 3)).astype(np.float32),
                segments=[Segment(0, min(n, 6), "reach")] if k == 0 else [],
            )
            writer.add(episode, "train" if k == 0 else "play")
    return path


def moving_square(frames: int) -> np.ndarray:
    """A bright square moving over a dark background: each frame tells which one it is."""
    video = np.full((frames, 16, 20, 3), 30, np.uint8)
    for k in range(frames):
        video[k, 4:12, k % 12 : k % 12 + 8] = 220
    return video


def review_cli(*args: str) -> tuple[int, str]:
    """`playseg review ...` as a user runs it; (exit code, stderr). A refusal exits at once."""
    done = subprocess.run(
        [sys.executable, "-m", "playseg_ros.cli", "review", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    return done.returncode, done.stderr.strip()


@pytest.fixture
def serve() -> Iterator[Any]:
    servers: list[ReviewServer] = []

    def run(dataset: Path, **options: Any) -> str:
        server, url = start(dataset, port=0, **options)
        servers.append(server)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        return url

    yield run
    for server in servers:
        server.shutdown()
        server.server_close()


def get(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers), error.read()


def test_video_is_encoded_once_and_served_in_ranges(tmp_path: Path, serve: Any) -> None:
    data = write_dataset(tmp_path / "d", (12, 8), images=True)
    url = serve(data)
    status, headers, whole = get(url + "api/episode/0/video/observation.images.top")
    assert status == 200 and headers["Content-Type"] == "video/mp4" and whole[4:8] == b"ftyp"
    status, headers, part = get(url + "api/episode/0/video/observation.images.top", {"Range": "bytes=10-99"})
    assert status == 206 and part == whole[10:100]
    assert headers["Content-Range"] == f"bytes 10-99/{len(whole)}"
    status, _, tail = get(url + "api/episode/0/video/observation.images.top", {"Range": "bytes=-16"})
    assert status == 206 and tail == whole[-16:]
    assert (
        get(url + "api/episode/0/video/observation.images.top", {"Range": f"bytes={len(whole)}-"})[0] == 416
    )
    cached = list((review_dir(data) / "video").glob("*.mp4"))
    assert len(cached) == 1
    mtime = cached[0].stat().st_mtime_ns
    get(url + "api/episode/0/video/observation.images.top")
    assert cached[0].stat().st_mtime_ns == mtime  # served from the cache, not encoded again
    import av

    with av.open(str(cached[0])) as container:
        frames = [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]
    assert len(frames) == 13  # one frame per observation
    original = PlayDataset.open(data).episode(0).images["observation.images.top"]
    errors = [np.abs(frames[5][:16, :20].astype(int) - original[k].astype(int)).mean() for k in range(13)]
    assert int(np.argmin(errors)) == 5 and errors[5] < 10  # lossy, but that frame


def test_a_long_episode_video_comes_in_chunks_encoded_on_demand(tmp_path: Path, serve: Any) -> None:
    import av

    data = write_dataset(tmp_path / "d", (44, 8), images=True)  # 45 observations: chunks of 20, 20, 5
    url = serve(data, video_chunk=20)
    assert json.loads(get(url + "api/episode/0")[2])["video_chunk"] == 20
    video = url + "api/episode/0/video/observation.images.top"
    status, _, last = get(video + "?chunk=2")
    assert status == 200 and last[4:8] == b"ftyp"
    status, _, body = get(video + "?chunk=3")
    assert status == 400 and "chunks 0..2" in json.loads(body)["error"]
    original = PlayDataset.open(data).episode(0).images["observation.images.top"]
    cache = review_dir(data) / "video"
    chunk_files = {len(f.read_bytes()): f for f in cache.glob("*.mp4")}
    with av.open(str(chunk_files[len(last)])) as container:
        frames = [frame.to_ndarray(format="rgb24")[:16, :20] for frame in container.decode(video=0)]
    assert len(frames) == 5  # observations 40..44 only
    for k, frame in enumerate(frames):
        errors = [np.abs(frame.astype(int) - original[j].astype(int)).mean() for j in range(45)]
        assert int(np.argmin(errors)) % 12 == (40 + k) % 12 and min(errors) < 10
    # the first chunk, and only what was asked (and the chunk after it, encoded ahead) is encoded
    assert get(video + "?chunk=0")[0] == 200 and get(video)[2] == get(video + "?chunk=0")[2]
    for _ in range(100):  # the chunk encoded ahead, in the background
        if len(list(cache.glob("*.mp4"))) == 3:
            break
        threading.Event().wait(0.1)
    assert len(list(cache.glob("*.mp4"))) == 3


def test_dataset_without_images_and_a_long_episode_load_in_windows(tmp_path: Path, serve: Any) -> None:
    data = write_dataset(tmp_path / "d", (30, LONG), images=False)
    url = serve(data)
    status, _, body = get(url + "api/episode/1")
    episode = json.loads(body)
    assert status == 200 and episode["cameras"] == [] and episode["num_steps"] == LONG
    assert len(body) < 10_000  # no per-step array in the episode itself
    status, _, body = get(url + "api/episode/1/signals?start=0&end=100001&points=800")
    signals = json.loads(body)
    assert status == 200 and len(signals["steps"]) <= 800 and signals["steps"][-1] > 99_000
    assert signals["names"] == ["state.0", "state.1", "state.2", "action.0", "action.1"]
    status, _, body = get(url + "api/episode/1/signals?start=50000&end=50010&points=800")
    window = json.loads(body)
    assert window["steps"] == list(range(50000, 50010))
    state = PlayDataset.open(data).episode(1).state
    np.testing.assert_allclose(window["values"][0], state[50000:50010, 0], atol=1e-5)
    status, _, body = get(url + "api/episode/1/video/observation.images.top")
    assert status == 400 and "no camera" in json.loads(body)["error"]


def test_an_episode_names_its_source_bag_or_generator(tmp_path: Path, serve: Any) -> None:
    from playseg_core.data.splits import SplitTargets
    from playseg_core.domains.babyai.generate import Preset, generate_dataset
    from playseg_core.domains.babyai.play import PlayConfig

    preset = Preset("mini", "test", PlayConfig(max_tasks=3), SplitTargets(3, 3, 0))
    generate_dataset(tmp_path / "generated", preset, seed=4, progress=False)
    url = serve(tmp_path / "generated")
    episode = json.loads(get(url + "api/episode/0")[2])
    assert episode["source"] == {
        "generator": "babyai",
        "preset": "mini",
        "seed": 4,
        "episode_seed": 4 * 10**9,
    }
    assert episode["source_text"] == "generated by babyai, preset mini, seed 4, episode seed 4000000000"

    source = {"bag": "/bags/run_01", "topics": ["/camera", "/joints"], "start_ns": 1_700_000_000_250_000_000}
    with DatasetWriter(tmp_path / "converted", ["reach"]) as writer:
        writer.add(Episode("run_01:0", np.zeros((3, 2), np.float32), source=source), "play")
    episode = json.loads(get(serve(tmp_path / "converted") + "api/episode/0")[2])
    assert episode["source_text"] == "bag /bags/run_01 (/camera, /joints), from 2023-11-14 22:13:20.250 UTC"


def test_a_token_guards_a_server_bound_beyond_localhost(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", (10,), images=False)
    server, url = start(data, host="0.0.0.0", port=0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        assert "?token=" in url
        port = server.server_address[1]
        assert get(f"http://127.0.0.1:{port}/api/info")[0] == 403
        assert get(f"http://127.0.0.1:{port}/api/info?token={url.split('token=')[1]}")[0] == 200
        assert get(f"http://127.0.0.1:{port}/api/episode/0")[0] == 403
        # the page and its script hold no data: they load, and the script sends the token with each call
        assert get(f"http://127.0.0.1:{port}/")[0] == 200
        assert b"token" in get(f"http://127.0.0.1:{port}/static/app.js")[2]
    finally:
        server.shutdown()
        server.server_close()


def test_a_localhost_server_refuses_what_another_site_could_send(tmp_path: Path, serve: Any) -> None:
    """Without a token, a page of another site in the same browser can neither read through the server
    (DNS rebinding: a foreign Host) nor write (a form or text/plain POST, a foreign Origin); bad values
    are one-line 400s, and nothing was written."""
    data = write_dataset(tmp_path / "d", (10,), images=False)
    url = serve(data)
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    body = json.dumps({"out": str(target)}).encode()

    def send(headers: dict[str, str], path: str = "api/export/mcap") -> int:
        request = urllib.request.Request(url + path, body, headers)
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                return response.status
        except urllib.error.HTTPError as error:
            return error.code

    assert send({"Content-Type": "text/plain"}) == 403
    assert send({"Content-Type": "application/json", "Origin": "https://evil.example"}) == 403
    assert get(url + "api/info", {"Host": "evil.example:8765"})[0] == 403
    assert target.read_text() == "keep me"
    assert get(url + "api/info")[0] == 200  # the page itself, from this machine
    status, _, reply = get(url + "api/episode/0/signals?start=abc")
    assert status == 400 and json.loads(reply)["error"]
    page = json.loads(get(url + "api/episode/0")[2])
    nan = '{"labels": [{"start": 0, "end": 2, "instruction": "reach", "confidence": NaN}], "version": "%s"}'
    request = urllib.request.Request(
        url + "api/episode/0/save", (nan % page["version"]).encode(), {"Content-Type": "application/json"}
    )
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=30)
    assert refused.value.code == 400 and "confidence" in json.loads(refused.value.read())["error"]
    assert get(url + "api/episode/0")[0] == 200  # still served


def test_saves_to_two_episodes_of_one_bag_do_not_conflict(tmp_path: Path, serve: Any) -> None:
    """Both episodes' labels live in the bag's one labels file; each episode has its own version, so a
    save to one leaves the other's page free to save, and a second save with a stale version is refused."""
    rng = np.random.default_rng(1)
    with DatasetWriter(tmp_path / "d", ["reach", "wave"]) as writer:
        for k, (n, begins) in enumerate(((10, 0.0), (12, 5.0))):  # one bag: the second starts at 5 s
            episode = Episode(
                f"run:{k}",
                rng.standard_normal((n, 2)).astype(np.float32),
                state=rng.standard_normal((n + 1, 3)).astype(np.float32),
                timestamps=begins + np.arange(n + 1) / 10.0,
                source={"bag": str(tmp_path / "run")},
            )
            writer.add(episode, "play")
    url = serve(tmp_path / "d")
    pages = [json.loads(get(url + f"api/episode/{i}")[2]) for i in (0, 1)]
    first = post(url + "api/episode/0/save", {"labels": [{"start": 0, "end": 4, "instruction": "reach"}],
                                               "version": pages[0]["version"]})  # fmt: skip
    second = post(url + "api/episode/1/save", {"labels": [{"start": 2, "end": 6, "instruction": "wave"}],
                                                "version": pages[1]["version"]})  # fmt: skip
    assert first["file"] == second["file"] and first["saved"] == second["saved"] == 1
    stale = {"labels": [], "version": pages[0]["version"]}
    with pytest.raises(urllib.error.HTTPError) as refused:
        post(url + "api/episode/0/save", stale)
    assert refused.value.code == 409
    assert [row["instruction"] for row in json.loads(get(url + "api/episode/1")[2])["labels"]] == ["wave"]


def test_bad_labels_file_names_its_line(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", (10,), images=False)
    labels = review_dir(data) / "labels"
    labels.mkdir(parents=True)
    (labels / "run:0.yaml").write_text(
        "times: from_start\nannotations:\n  - {start: 0.0, end: 0.4, instruction: reach}\n"
        "  - {start: 0.5, end: zero, instruction: wave}\n"
    )
    code, err = review_cli(str(data), "--port", "0")
    assert code == 1 and err.count("\n") == 0
    assert "run:0.yaml', line 4: key 'end': must be a number" in err


def test_a_model_of_other_features_is_refused_at_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with_images = PlayDataset.open(write_dataset(tmp_path / "images", (12,), images=True))
    model = untrained_model(tmp_path / "ps.pt", with_images.features, with_images.episode(0))
    data = write_dataset(tmp_path / "d", (10,), images=False)
    code, err = review_cli(str(data), "--model", str(model), "--port", "0")
    assert code == 1 and err.count("\n") == 0 and "observation.images.top" in err and "ps.pt" in err


def test_a_port_in_use_or_a_bad_video_chunk_is_one_line(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", (10,), images=False)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code, err = review_cli(str(data), "--port", str(port))
    assert code == 1 and err.count("\n") == 0 and f"--port {port}: cannot listen on 127.0.0.1:{port}" in err
    code, err = review_cli(str(data), "--port", "0", "--video-chunk", "0")
    assert code == 1 and err.count("\n") == 0 and "--video-chunk 0: must be at least 1 frame" in err


def post(url: str, body: dict[str, Any]) -> dict[str, Any]:
    request = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read())


def finished(url: str, job: str) -> dict[str, Any]:
    """Poll a background job until it is no longer running (bounded: a hung job fails the test)."""
    for _ in range(1200):
        state = json.loads(get(url + "api/jobs")[2])[job]
        if state["state"] != "running":
            return state
        time.sleep(0.25)
    raise AssertionError(f"{job} still running: {state}")


@pytest.mark.slow  # trains a model
def test_retrain_reproposes_and_export_writes_lerobot(
    bags: dict[str, Path], tmp_path: Path, serve: Any
) -> None:
    from test_convert_segment import convert_cli

    assert convert_cli([bags["play"], bags["annotated"]], tmp_path / "data", bags["mapping"]) == 0
    url = serve(tmp_path / "data")
    info = json.loads(get(url + "api/info")[2])
    play = next(row["index"] for row in info["episodes"] if row["episode_id"] == "play:0")
    assert info["model"] is None and json.loads(get(url + f"api/episode/{play}")[2])["proposals"] == []
    # the reviewer labels the start of the play episode, then retrains
    page = json.loads(get(url + f"api/episode/{play}")[2])
    post(
        url + f"api/episode/{play}/save",
        {"labels": [{"start": 0, "end": 9, "instruction": "wave"}], "version": page["version"]},
    )
    assert post(url + "api/retrain", {"steps": 12})["state"] == "running"
    job = finished(url, "retrain")
    assert job["state"] == "done", job
    model = Path(job["result"]["model"])
    assert model.is_file()
    proposals = json.loads(get(url + f"api/episode/{play}")[2])["proposals"]
    assert proposals and all(p["start"] >= 9 for p in proposals)  # none over the reviewer's label
    digest = proposals[0]["provenance"].removeprefix("model:")
    assert len(digest) == 12 and digest in hashlib.sha256(model.read_bytes()).hexdigest()
    # export: the preview shows the language rows; the export is LeRobot v3.0
    preview = json.loads(get(url + "api/export/preview")[2])["episodes"]
    contents = {row["content"] for episode in preview for row in episode["rows"]}
    assert {"wave", "pick up the cup", "put the cup down"} <= contents
    post(url + "api/export", {"out": str(tmp_path / "lerobot")})
    job = finished(url, "export")
    assert job["state"] == "done", job
    exported = json.loads((tmp_path / "lerobot" / "meta" / "info.json").read_text())
    assert exported["codebase_version"] == "v3.0" and exported["total_episodes"] == 2


def test_bags_are_converted_on_the_fly_and_cached(bags: dict[str, Path], tmp_path: Path) -> None:
    both = [str(tmp_path / "bags" / name) for name in ("play", "annotated")]
    shutil.copytree(bags["play"], both[0])
    shutil.copytree(bags["annotated"], both[1])

    def run() -> tuple[list[str], dict[str, Any]]:
        command = [
            sys.executable,
            "-m",
            "playseg_ros.cli",
            "review",
            *both,
            "--mapping",
            str(bags["mapping"]),
            "--port",
            "0",
        ]
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert process.stdout is not None
        try:
            lines = [process.stdout.readline()]
            while lines[-1] and not lines[-1].startswith("playseg review: http"):
                lines.append(process.stdout.readline())
            assert lines[-1], process.stderr.read() if process.stderr else ""
            return lines, json.loads(get(lines[-1].split()[2] + "api/info")[2])
        finally:
            process.terminate()
            process.wait(timeout=10)

    lines, info = run()
    assert "2 converted, 0 skipped" in lines[0]
    assert sorted(row["episode_id"] for row in info["episodes"]) == ["annotated:0", "play:0"]
    assert info["dataset"] == str(tmp_path / "bags" / "play.review" / "data")
    lines, _ = run()
    assert "0 converted, 2 skipped" in lines[0]  # the cached conversion


def test_labels_exported_as_mcap_read_back_on_the_recording_clock(
    bags: dict[str, Path], tmp_path: Path, serve: Any
) -> None:
    from mcap.reader import make_reader
    from test_convert_segment import convert_cli

    assert convert_cli([bags["annotated"]], tmp_path / "data", bags["mapping"]) == 0
    url = serve(tmp_path / "data")
    dataset = PlayDataset.open(tmp_path / "data")
    labels = [(3, 12, "pick up the cup"), (12, 25, "put the cup down")]
    assert [(s.start, s.end, s.instruction) for s in dataset.segments(0)] == labels
    written = post(url + "api/export/mcap", {"out": str(tmp_path / "segments.mcap")})
    start_ns = dataset.records[0].source["start_ns"]
    times = start_ns + np.round(dataset.timestamps(0) * 1e9).astype(np.int64)
    with open(tmp_path / "segments.mcap", "rb") as handle:
        reader = make_reader(handle)
        messages = [
            (channel.topic, schema.name, message.log_time, json.loads(message.data))
            for schema, channel, message in reader.iter_messages()
        ]
    assert written["messages"] == len(messages)
    states = [(t, m["data"]) for topic, _, t, m in messages if topic == "/playseg/instruction"]
    assert [t for t, _ in states] == times.tolist()
    expected = [
        "pick up the cup" if 3 <= k < 12 else "put the cup down" if 12 <= k < 25 else ""
        for k in range(len(times))
    ]
    assert [text for _, text in states] == expected
    logs = [(name, t, m["message"]) for topic, name, t, m in messages if topic == "/playseg/boundaries"]
    assert logs == [
        ("foxglove.Log", int(times[3]), "start: pick up the cup"),
        ("foxglove.Log", int(times[12]), "end: pick up the cup"),
        ("foxglove.Log", int(times[12]), "start: put the cup down"),
        ("foxglove.Log", int(times[25]), "end: put the cup down"),
    ]
