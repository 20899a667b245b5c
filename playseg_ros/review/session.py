"""What the review page shows and changes: the episodes, their labels and the model's proposals, the
queue, the signals, and the background jobs (proposing, retraining, exporting)."""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.features import ACTION, STATE
from playseg_core.data.splits import ANNOTATED_SPLITS
from playseg_core.errors import PlaysegError
from playseg_ros.convert.annotations import model_provenance
from playseg_ros.review.store import Label, LabelStore

MAX_SIGNALS = 12
"""Signal channels plotted (the first ones of the state, then of the action)."""
MAX_POINTS = 4000
"""The most samples one signals request returns: a long episode is loaded a window at a time."""


@dataclass
class Proposal:
    """A model's segment, waiting for a reviewer to accept, change or reject it."""

    start: int
    end: int
    instruction: str
    confidence: float
    provenance: str

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Job:
    """A background job's state as the page polls it."""

    name: str
    state: str = "idle"  # idle, running, done, failed
    progress: str = ""
    error: str | None = None
    result: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


class ReviewSession:
    """One dataset under review: labels in ``labels_dir``, videos cached in ``cache_dir``; proposals from
    the dataset's own model segments and, with ``model``, from that PS checkpoint (computed in the
    background for the episodes without labels)."""

    def __init__(
        self, dataset_path: Path, labels_dir: Path, cache_dir: Path, model: Path | None = None
    ) -> None:
        self.dataset = PlayDataset.open(dataset_path)
        self.labels_dir, self.cache_dir = labels_dir, cache_dir
        self.store = LabelStore(self.dataset, labels_dir)
        self.store.check_files()
        self.model_path = model
        self.segmenter = self._load_model(model) if model is not None else None
        self.proposals: dict[int, list[Proposal]] = self._dataset_proposals()
        self.jobs: dict[str, Job] = {name: Job(name) for name in ("propose", "retrain", "export")}
        self._lock = threading.Lock()
        self.signal_names = self._signal_names()

    def _load_model(self, path: Path) -> Any:
        from playseg_core.baselines.common import SegmentOptions
        from playseg_core.baselines.registry import load_segmenter

        segmenter = load_segmenter("ps", path, SegmentOptions())
        segmenter.check_features(self.dataset.features, f"model {path}")
        return segmenter

    def _dataset_proposals(self) -> dict[int, list[Proposal]]:
        """The segments a model wrote into the dataset (`playseg segment`, `convert --segment`): those of the
        episodes outside the annotated splits."""
        meta = self.dataset.info.get("meta", {})
        by_model = "segmented_by" in meta or bool((meta.get("convert") or {}).get("segmentation"))
        proposals: dict[int, list[Proposal]] = {}
        if not by_model:
            return proposals
        for index, record in enumerate(self.dataset.records):
            if record.split in ANNOTATED_SPLITS:
                continue
            proposals[index] = [
                Proposal(s.start, s.end, s.instruction, float(s.confidence), "model")
                for s in self.dataset.segments(index, truth=True)
                if s.instruction
            ]
        return proposals

    # ----------------------------------------------------------------------------------------------
    # What the page reads

    @property
    def instructions(self) -> list[str]:
        """The vocabulary the relabel box completes from: the dataset's, the model's and every saved label's."""
        vocabulary = set(self.dataset.instructions)
        if self.segmenter is not None:
            vocabulary.update(self.segmenter.instructions)
        for index in range(len(self.dataset)):
            vocabulary.update(label.instruction for label in self.store.initial_labels(index))
        return sorted(vocabulary)

    def summary(self) -> list[dict[str, Any]]:
        """Every episode: id, split, steps, labelled share of its steps, review status, its proposals'
        lowest confidence; in queue order (unreviewed first, lowest confidence first)."""
        state = self.store.state()
        rows = []
        for index, record in enumerate(self.dataset.records):
            labels = self.store.initial_labels(index)
            proposals = self.open_proposals(index, state)
            covered = sum(label.end - label.start for label in labels)
            rows.append(
                {
                    "index": index,
                    "episode_id": record.episode_id,
                    "split": record.split,
                    "num_steps": record.num_steps,
                    "coverage": covered / max(record.num_steps, 1),
                    "reviewed": bool(state.get(record.episode_id, {}).get("reviewed", False)),
                    "proposals": len(proposals),
                    "min_confidence": min((p.confidence for p in proposals), default=None),
                }
            )
        return sorted(rows, key=_queue_key)

    def open_proposals(self, index: int, state: dict[str, Any] | None = None) -> list[Proposal]:
        """Proposals not rejected and not overlapping a label."""
        state = self.store.state() if state is None else state
        rejected = {
            tuple(r) for r in state.get(self.dataset.records[index].episode_id, {}).get("rejected", [])
        }
        labels = self.store.initial_labels(index)
        return [
            p
            for p in self.proposals.get(index, [])
            if (p.start, p.end, p.instruction) not in rejected
            and not any(label.start < p.end and p.start < label.end for label in labels)
        ]

    def episode(self, index: int) -> dict[str, Any]:
        self.check_index(index)
        record = self.dataset.records[index]
        times = self.dataset.timestamps(index)
        state = self.store.state().get(record.episode_id, {})
        return {
            "index": index,
            "episode_id": record.episode_id,
            "split": record.split,
            "num_steps": record.num_steps,
            "fps": float(self.dataset.features.fps or 10.0),
            "start_time": float(times[0]),
            "end_time": float(times[-1]),
            "source": record.source,
            "cameras": list(self.dataset.features.cameras),
            "signals": self.signal_names,
            "labels": [label.to_json() for label in self.store.initial_labels(index)],
            "proposals": [p.to_json() for p in self.open_proposals(index)],
            "reviewed": bool(state.get("reviewed", False)),
            "rejected": state.get("rejected", []),
            "version": self.store.version(index),
            "labels_file": str(self.store.file_of(index)),
        }

    def _signal_names(self) -> list[str]:
        names = []
        for feature in (STATE, ACTION):
            if feature not in self.dataset.features.by_name:
                continue
            spec = self.dataset.features[feature]
            size = int(np.prod(spec.shape)) if spec.shape else 1
            axis = (
                list(spec.names) if spec.names and len(spec.names) == size else [str(i) for i in range(size)]
            )
            names += [f"{feature.split('.')[-1]}.{name}" for name in axis]
        return names[:MAX_SIGNALS]

    def signals(self, index: int, start: int, end: int, points: int) -> dict[str, Any]:
        """The plotted channels over observations [start, end), at most ``points`` samples (every k-th)."""
        self.check_index(index)
        record = self.dataset.records[index]
        start, end = max(0, start), min(record.num_steps + 1, max(end, start + 1))
        stride = max(1, -(-(end - start) // max(1, min(points, MAX_POINTS))))
        steps = np.arange(start, end, stride)
        episode = self.dataset.episode(index)
        series: list[np.ndarray] = []
        if episode.state is not None:
            series.append(np.asarray(episode.state[start:end:stride], np.float64).reshape(len(steps), -1))
        actions = np.asarray(episode.actions, np.float64).reshape(record.num_steps, -1)
        taken = np.minimum(steps, record.num_steps - 1) if record.num_steps else steps
        series.append(actions[taken] if record.num_steps else np.zeros((len(steps), actions.shape[1])))
        values = np.concatenate(series, axis=1)[:, : len(self.signal_names)]
        return {"steps": steps.tolist(), "values": np.round(values.T, 5).tolist(), "names": self.signal_names}

    def check_index(self, index: int) -> None:
        if not 0 <= index < len(self.dataset):
            raise PlaysegError(f"episode index {index} out of range (0..{len(self.dataset) - 1})")

    # ----------------------------------------------------------------------------------------------
    # What the page changes

    def save(self, index: int, body: dict[str, Any]) -> dict[str, Any]:
        """Save the page's labels and review state of episode ``index`` (VersionConflict when its file
        changed since the page loaded it)."""
        self.check_index(index)
        record = self.dataset.records[index]
        raw = body.get("labels")
        if not isinstance(raw, list):
            raise PlaysegError("save: field 'labels' must be a list")
        labels = sorted(
            (Label.from_json(item, record.num_steps, f"labels[{i}]") for i, item in enumerate(raw)),
            key=lambda label: label.start,
        )
        for previous, label in zip(labels, labels[1:], strict=False):
            if label.start < previous.end:
                raise PlaysegError(
                    f"labels [{previous.start}, {previous.end}) and [{label.start}, {label.end}) overlap"
                )
        version = self.store.save(index, labels, str(body.get("version", "")))
        rejected = [
            [int(r[0]), int(r[1]), str(r[2])]
            for r in body.get("rejected", [])
            if isinstance(r, list) and len(r) == 3 and all(isinstance(v, int) for v in r[:2])
        ]
        self.store.save_state(record.episode_id, bool(body.get("reviewed", False)), rejected)
        return {"version": version, "saved": len(labels), "file": str(self.store.file_of(index))}

    # ----------------------------------------------------------------------------------------------
    # Background jobs

    def start_job(self, name: str, target: Any, *args: Any) -> Job:
        with self._lock:
            job = self.jobs[name]
            if job.state == "running":
                raise PlaysegError(f"{name} is already running")
            self.jobs[name] = job = Job(name, "running")

        def run() -> None:
            try:
                job.result = target(job, *args) or {}
                job.state = "done"
            except Exception as error:  # noqa: BLE001 (shown on the page; the server goes on)
                job.state, job.error = "failed", " ".join(str(error).split()) or type(error).__name__

        threading.Thread(target=run, name=f"review-{name}", daemon=True).start()
        return job

    def propose(self, job: Job, indices: list[int] | None = None) -> dict[str, Any]:
        """Propose segments for the episodes not yet reviewed (the page shows those outside their labels)."""
        if self.segmenter is None:
            raise PlaysegError("no model: start `playseg review` with --model PS.pt, or retrain")
        state = self.store.state()
        todo = [
            i
            for i in (range(len(self.dataset)) if indices is None else indices)
            if not state.get(self.dataset.records[i].episode_id, {}).get("reviewed")
        ]
        provenance = model_provenance(self.model_path) if self.model_path else "model"
        for done, index in enumerate(todo):
            job.progress = f"proposing {done + 1}/{len(todo)}"
            segments = self.segmenter.segment(self.dataset.episode(index))
            self.proposals[index] = [
                Proposal(s.start, s.end, s.instruction, float(s.confidence), provenance)
                for s in segments
                if s.instruction
            ]
        job.progress = f"{len(todo)} episode(s) proposed"
        return {"episodes": len(todo)}


def _queue_key(row: dict[str, Any]) -> tuple[Any, ...]:
    confidence = row["min_confidence"]
    return (row["reviewed"], confidence is None, confidence if confidence is not None else 0.0, row["index"])
