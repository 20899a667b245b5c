"""`playseg review DATASET`: open the dataset, start the server, print the URL; and the page's actions
that reach beyond one episode (retrain and re-propose, export to LeRobot v3.0)."""

from __future__ import annotations

import secrets
import subprocess
import sys
from pathlib import Path
from typing import Any

from playseg_core.data.dataset import DatasetWriter, PlayDataset, is_dataset
from playseg_core.data.episode import Segment
from playseg_core.data.splits import annotated_splits
from playseg_core.errors import PlaysegError
from playseg_ros.review.server import ReviewServer
from playseg_ros.review.session import Job, ReviewSession
from playseg_ros.review.video import CHUNK_FRAMES

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
RETRAIN_STEPS = 300
"""Optimiser steps of a retrain from the page (the CLI's `playseg train --max-steps`)."""


def review_dir(dataset: Path) -> Path:
    """Where the review of ``dataset`` keeps its labels, videos and models: ``<dataset>.review`` beside it."""
    dataset = dataset.resolve()  # `playseg review .` too
    return dataset.with_name(f"{dataset.name}.review")


class ReviewActions:
    """The page's actions on the whole dataset."""

    def __init__(self, session: ReviewSession, work: Path) -> None:
        self.session, self.work = session, work

    def info(self) -> dict[str, Any]:
        session = self.session
        return {
            "dataset": str(session.dataset.path),
            "labels_dir": str(session.labels_dir),
            "instructions": session.instructions,
            "cameras": list(session.dataset.features.cameras),
            "model": str(session.model_path) if session.model_path else None,
            "episodes": session.summary(),
            "jobs": {name: job.to_json() for name, job in session.jobs.items()},
        }

    def reviewed_dataset(self, out: Path) -> PlayDataset:
        """The dataset with the reviewed labels as its annotations: labelled episodes in train/val, the others
        in play."""
        session = self.session
        labels = {i: session.store.initial_labels(i) for i in range(len(session.dataset))}
        ids = [session.dataset.records[i].episode_id for i, found in labels.items() if found]
        if not ids:
            raise PlaysegError("no episode has labels yet: label some segments and save first")
        splits = annotated_splits(ids)
        instructions = sorted({label.instruction for found in labels.values() for label in found})
        dataset = session.dataset
        with DatasetWriter(out, instructions, meta={"reviewed_from": str(dataset.path)}, overwrite=is_dataset(out),
                           features=dataset.features, domain=dataset.domain) as writer:  # fmt: skip
            for index, found in labels.items():
                episode = dataset.episode(index).with_segments(
                    [Segment(label.start, label.end, label.instruction) for label in found]
                )
                writer.add(episode, splits.get(episode.episode_id, "play"), dataset.records[index].extra)
        return PlayDataset.open(out)

    def retrain(self, body: dict[str, Any]) -> Job:
        steps = int(body.get("steps") or RETRAIN_STEPS)
        return self.session.start_job("retrain", self._retrain, steps)

    def _retrain(self, job: Job, steps: int) -> dict[str, Any]:
        """Train PS on the current labels with `playseg train` (a child process, its progress shown), then
        propose again for the unreviewed episodes without labels."""
        job.progress = "writing the labelled episodes"
        data = self.reviewed_dataset(self.work / "train-data")
        if not data.episode_indices("train"):
            raise PlaysegError("training needs labelled episodes in train: label more episodes")
        models = self.work / "models"
        models.mkdir(parents=True, exist_ok=True)
        model = models / f"ps-{len(list(models.glob('ps-*.pt')))}.pt"  # one per retraining, kept
        command = [sys.executable, "-m", "playseg_ros.cli", "train", "--data", str(data.path), "--out", str(model),
                   "--max-steps", str(steps), "--overwrite"]  # fmt: skip
        job.progress = "training"
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert process.stdout is not None
        last = ""
        for line in process.stdout:
            if line.strip():
                last = line.strip()
                job.progress = f"training: {last[-160:]}"
        if process.wait() != 0:
            raise PlaysegError(f"playseg train failed: {last}")
        session = self.session
        session.segmenter, session.model_path = session._load_model(model), model
        session.propose(job)
        return {"model": str(model)}

    def export_preview(self, limit: int = 3) -> dict[str, Any]:
        """The ``language_persistent`` rows of the first labelled episodes, as the export writes them."""
        from playseg_ros.convert.lerobot import language_rows

        session, rows = self.session, []
        fps = float(session.dataset.features.fps or 10.0)
        for index in range(len(session.dataset)):
            labels = session.store.initial_labels(index)
            if not labels:
                continue
            record = session.dataset.records[index]
            segments = [Segment(label.start, label.end, label.instruction) for label in labels]
            episode_rows = language_rows(segments, record.num_steps + 1, fps)
            rows.append({"episode_id": record.episode_id, "rows": episode_rows[:12]})
            if len(rows) == limit:
                break
        return {"episodes": rows}

    def export_mcap(self, body: dict[str, Any]) -> dict[str, Any]:
        """The labels as an MCAP for Foxglove (review/foxglove.py), beside the review by default."""
        from playseg_ros.review.foxglove import write_segments_mcap

        out = Path(str(body.get("out") or self.work / "segments.mcap"))
        session = self.session
        labels = {i: session.store.initial_labels(i) for i in range(len(session.dataset))}
        segments = {
            i: [Segment(label.start, label.end, label.instruction) for label in found]
            for i, found in labels.items()
            if found
        }
        return {"out": str(out), "messages": write_segments_mcap(session.dataset, segments, out)}

    def export(self, body: dict[str, Any]) -> Job:
        out = Path(str(body.get("out") or self.work / "lerobot"))
        return self.session.start_job("export", self._export, out)

    def _export(self, job: Job, out: Path) -> dict[str, Any]:
        from playseg_ros.convert.lerobot import export_lerobot

        job.progress = "writing the reviewed dataset"
        data = self.reviewed_dataset(self.work / "export-data")
        job.progress = f"exporting to {out}"
        summary = export_lerobot(data, out, overwrite=True)
        job.progress = f"{out}: LeRobot v3.0"
        return {"out": str(out), "summary": str(summary)}


def dataset_of(inputs: list[Path], mapping: Path | None) -> tuple[Path, Path]:
    """The dataset to review and the review's directory: ``inputs`` when it is one dataset; else bags,
    converted (through ``mapping``, or as playseg play bags) into ``<first input>.review/data``. A rerun
    converts only the bags that are new or changed (`playseg convert` resumes)."""
    if len(inputs) == 1 and is_dataset(inputs[0]):
        if mapping is not None:
            raise PlaysegError(f"--mapping is for bags; {inputs[0]} is a dataset already")
        return inputs[0], review_dir(inputs[0])
    from playseg_ros.convert import convert, load_mapping

    missing = [path for path in inputs if not path.exists()]
    if missing:
        raise FileNotFoundError(f"{missing[0]}: no such dataset or bag")
    work = review_dir(inputs[0])
    summary = convert(inputs, work / "data", load_mapping(mapping) if mapping else None, progress=False)
    for report in summary.failed:
        print(f"playseg review: failed: {report.error}", file=sys.stderr)
    if not is_dataset(work / "data"):
        raise PlaysegError(f"{inputs[0]}: no bag converted (give --mapping MAP.yaml for robot bags)")
    print(summary.text(), flush=True)
    return work / "data", work


def start(
    dataset: Path,
    model: Path | None = None,
    labels: Path | None = None,
    host: str = "127.0.0.1",
    port: int = 8765,
    token: str | None = None,
    work: Path | None = None,
    video_chunk: int = CHUNK_FRAMES,
) -> tuple[ReviewServer, str]:
    """The server (not yet serving) and its URL. A host other than localhost gets a random token in the URL
    unless ``token`` is given. ``work`` holds labels, videos and models (default `review_dir`);
    ``video_chunk``: observations per video file (video.py)."""
    work = work or review_dir(dataset)
    session = ReviewSession(dataset, labels or work / "labels", work / "video", model, video_chunk)
    if token is None and host not in LOCAL_HOSTS:
        token = secrets.token_urlsafe(16)
    try:
        server = ReviewServer((host, port), session, token, None)
    except OSError as error:
        raise PlaysegError(f"--port {port}: cannot listen on {host}:{port} ({error.strerror or error}); "
                           "choose another port") from None  # fmt: skip
    server.actions = ReviewActions(session, work)
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown}:{server.server_address[1]}/" + (f"?token={token}" if token else "")
    return server, url


def review(
    inputs: list[str],
    model: str | None,
    labels: str | None,
    host: str,
    port: int,
    mapping: str | None = None,
    video_chunk: int | None = None,
) -> int:
    """`playseg review`: serve until interrupted."""
    video_chunk = CHUNK_FRAMES if video_chunk is None else video_chunk
    if video_chunk < 1:
        raise PlaysegError(f"--video-chunk {video_chunk}: must be at least 1 frame")
    path, work = dataset_of([Path(p) for p in inputs], Path(mapping) if mapping else None)
    server, url = start(
        path,
        Path(model) if model else None,
        Path(labels) if labels else None,
        host,
        port,
        work=work,
        video_chunk=video_chunk,
    )
    if server.session.segmenter is not None:
        server.session.start_job("propose", server.session.propose)
    print(f"playseg review: {url}  (labels in {server.session.labels_dir}; Ctrl-C stops)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
