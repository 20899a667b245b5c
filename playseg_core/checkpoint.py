"""Checkpoints of every model playseg trains: the PS model, the labelling model and policies.

One file format: a dict of plain tensors, numbers and strings, read with ``torch.load(weights_only=True)``
(a checkpoint is untrusted input)::

    format    "playseg-checkpoint"
    version   CHECKPOINT_VERSION
    kind      "ps" | "labeller" | "policy" | "unloc" | "tridet" (the window baselines, baselines/)
    config    the model's full configuration (JSON-like), including which features it reads
    features  the data features the model reads, as the training data declared them (data/features.py)
    state_dict
    meta      plain data: training settings, history, calibration, version numbers, ...

`Checkpoint.check_features` compares ``features`` with a dataset's; a mismatch is a FeatureError naming
the feature. Building the model from ``config`` is the owner's job (ps/model.py, a domain's policy).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from playseg_core.data.features import FeatureError, Features
from playseg_core.errors import PlaysegError


def file_digest(path: str | Path, suffix: bytes = b"") -> str:
    """sha256 (hex) of a file's bytes followed by ``suffix``: what a result made from a checkpoint (or
    another file) records, so that one made from a file replaced since is found stale."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    digest.update(suffix)
    return digest.hexdigest()


CHECKPOINT_FORMAT = "playseg-checkpoint"
CHECKPOINT_VERSION = 1
Kind = Literal["ps", "labeller", "policy", "unloc", "tridet"]
KINDS: tuple[str, ...] = ("ps", "labeller", "policy", "unloc", "tridet")


class CheckpointError(PlaysegError):
    """A file that is not a usable playseg checkpoint; the message names the file."""


@dataclass
class Checkpoint:
    kind: Kind
    config: dict[str, Any]
    features: Features
    state_dict: dict[str, torch.Tensor]
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None  # where it was read from

    @property
    def feature_names(self) -> list[str]:
        return sorted(self.features.by_name)

    def check_features(self, data: Features, names: Iterable[str] | None = None) -> None:
        """FeatureError naming the first feature the model reads that ``data`` lacks or declares otherwise."""
        what = f"checkpoint {self.path}" if self.path else f"{self.kind} checkpoint"
        self.features.check_compatible(data, self.feature_names if names is None else names, what)


def save_checkpoint(path: str | os.PathLike[str], checkpoint: Checkpoint) -> Path:
    """Write ``checkpoint`` to ``path`` atomically (a temporary file renamed into place)."""
    if checkpoint.kind not in KINDS:
        raise PlaysegError(f"checkpoint kind must be one of {KINDS}, got {checkpoint.kind!r}")
    path = Path(path)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "kind": checkpoint.kind,
        "config": checkpoint.config,
        "features": checkpoint.features.to_json(),
        "state_dict": {name: t.detach().cpu().clone() for name, t in checkpoint.state_dict.items()},
        "meta": dict(checkpoint.meta),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_checkpoint(path: str | os.PathLike[str], kinds: Iterable[str] = KINDS) -> Checkpoint:
    """Read and check a checkpoint of one of ``kinds``; CheckpointError naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        what = "is a directory, not a checkpoint file" if path.is_dir() else "no such file"
        raise CheckpointError(f"checkpoint {path}: {what}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # corrupt, truncated, or carrying objects weights_only refuses
        # torch's own message runs to many lines and suggests weights_only=False, which is not an option
        # for an untrusted file: name the file and the kind of failure only.
        raise CheckpointError(
            f"checkpoint {path}: cannot be read safely (not a torch file, damaged, or holding objects "
            f"other than tensors and plain data: {type(error).__name__})"
        ) from error
    if not isinstance(payload, Mapping) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"checkpoint {path}: not a {CHECKPOINT_FORMAT} file (written by an older playseg? retrain it)"
        )
    if payload.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"checkpoint {path}: version {payload.get('version')!r}; this playseg reads {CHECKPOINT_VERSION}"
        )
    kinds = tuple(kinds)
    if payload.get("kind") not in kinds:
        raise CheckpointError(
            f"checkpoint {path}: a {payload.get('kind')!r} checkpoint, expected {' or '.join(kinds)}"
        )
    missing = {"config", "features", "state_dict", "meta"} - set(payload)
    if missing:
        raise CheckpointError(f"checkpoint {path}: lacks {sorted(missing)}")
    try:
        features = Features.from_json(payload["features"])
    except FeatureError as error:
        raise CheckpointError(f"checkpoint {path}: {error}") from None
    if not all(isinstance(payload[key], Mapping) for key in ("config", "state_dict", "meta")):
        raise CheckpointError(f"checkpoint {path}: config, state_dict and meta must be mappings")
    return Checkpoint(
        kind=payload["kind"],
        config=dict(payload["config"]),
        features=features,
        state_dict=dict(payload["state_dict"]),
        meta=dict(payload["meta"]),
        path=path,
    )
