"""`playseg convert --segment MODEL`: the unannotated episodes of a bag cut into labelled segments by a
segmentation model (playseg_core/baselines/registry.py: ps, unloc, tridet, random, changepoint).

Which episodes: an episode without any human annotation is segmented; its segments are stored with
their label confidence and segment log-score, keeping only those the spec's keep rule keeps
(ps/labelling.py `KEEP_RULES`; default ``label``: confidence >= the model's calibrated label threshold,
0 for an uncalibrated checkpoint: all), and it stays in the ``play`` split (the segments are
predictions, not ground truth). An episode with at least one human annotation, even one covering a
few of its steps, is **not** segmented: it keeps exactly its human segments (in ``train``), and its
unannotated stretches stay unlabelled; a note says how many of its steps the annotations cover. Mixing predicted and human labels inside one episode would make predictions look
like ground truth to `playseg train`.

The model is loaded once per process (a worker converts many bags) and checked against each bag's
features; a bag the model cannot read fails with the bag and the feature named.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

from playseg_core.data.episode import Episode
from playseg_core.data.features import Features
from playseg_core.errors import PlaysegError
from playseg_ros.convert.errors import ConvertError

if TYPE_CHECKING:
    from playseg_core.baselines.common import Segmenter
    from playseg_core.ps.labelling import KeepRule


@dataclass(frozen=True)
class SegmentationSpec:
    """Which model segments the unannotated episodes: checkpoint, method, the seed of methods that draw
    random windows, which of its segments are kept (a keep rule), and a digest of all four (a dataset
    segmented by another model, or kept by another rule, is not resumed)."""

    model: Path
    method: str
    seed: int
    digest: str
    keep: str = "label"
    threads: int | None = None  # torch threads per worker (None: torch's default); not in the digest
    device: str = "auto"  # where the model runs (training/device.py); not in the digest

    @classmethod
    def of(
        cls,
        model: str | Path,
        method: str = "ps",
        seed: int = 0,
        keep: str = "label",
        device: str = "auto",
    ) -> SegmentationSpec:
        """The spec of checkpoint ``model``; FileNotFoundError / ValueError (one line) before any bag is
        read when the file, the method, the keep rule or the device is wrong (the rule's threshold is
        checked when the model is loaded: `keep_rule`)."""
        from playseg_core.baselines.registry import get_method  # torch: only when segmenting
        from playseg_core.checkpoint import file_digest
        from playseg_core.ps.labelling import KeepRule
        from playseg_core.training.device import resolve_device

        get_method(method)
        resolve_device(device)
        try:
            KeepRule(keep)
        except ValueError as error:
            raise PlaysegError(f"--keep: {error}") from None
        path = Path(model).resolve()
        if not path.is_file():
            what = "is a directory, not a checkpoint file" if path.is_dir() else "no such checkpoint file"
            raise FileNotFoundError(f"--segment {model}: {what}")
        # The default rule leaves the digest as it was before rules existed: those datasets resume.
        suffix = f"|{method}|{seed}" + ("" if keep == "label" else f"|{keep}")
        return cls(path, method, seed, file_digest(path, suffix.encode()), keep, device=device)

    def describe(self) -> dict[str, object]:
        """What a dataset's meta.convert records about the segmentation."""
        return {"model": str(self.model), "method": self.method, "seed": self.seed, "digest": self.digest}


@cache
def _loaded(spec: SegmentationSpec) -> Segmenter:
    import torch

    from playseg_core.baselines.common import SegmentOptions
    from playseg_core.baselines.registry import load_segmenter as load_method

    if spec.threads is not None:  # several workers on few cores: one thread each, not cores x workers
        torch.set_num_threads(spec.threads)

    return load_method(spec.method, spec.model, SegmentOptions(seed=spec.seed, device=spec.device))


def load_segmenter(spec: SegmentationSpec) -> Segmenter:
    """The segmenter of ``spec``, loaded once per process."""
    return _loaded(spec)


@dataclass
class SegmentedEpisodes:
    episodes: list[Episode]
    segmented: int  # episodes the model segmented
    model_segments: int  # segments it gave that its keep rule keeps (stored)
    not_kept: int  # segments it gave that the rule does not keep (not stored)
    notes: list[str]


def segment_unannotated(
    bag: Path, episodes: list[Episode], features: Features | None, spec: SegmentationSpec
) -> SegmentedEpisodes:
    """``episodes`` with every unannotated one segmented by the model of ``spec`` (see the module
    docstring); ConvertError naming the bag when the model cannot read its features."""
    segmenter = load_segmenter(spec)
    if features is not None:
        try:
            segmenter.check_features(features, f"model {spec.model}")
        except ValueError as error:
            raise ConvertError(bag, str(error)) from None
    rule = keep_rule(spec)
    result = SegmentedEpisodes([], 0, 0, 0, [])
    for episode in episodes:
        if episode.segments:
            covered = sum(s.length for s in episode.segments)
            if covered < episode.num_steps:
                result.notes.append(
                    f"episode {episode.episode_id!r}: annotated ({len(episode.segments)} segment(s), "
                    f"{covered} of {episode.num_steps} steps); kept its human labels, not segmented"
                )
            result.episodes.append(episode)
            continue
        segments = segmenter.segment(episode)
        kept = [s for s in segments if rule.keeps(s)]
        result.segmented += 1
        result.model_segments += len(kept)
        result.not_kept += len(segments) - len(kept)
        result.episodes.append(episode.with_segments(kept))
    if result.not_kept:
        result.notes.append(
            f"segmented by {spec.model.name}: {result.not_kept} segment(s) not stored (kept: "
            f"{rule.describe()})"
        )
    return result


def keep_rule(spec: SegmentationSpec) -> KeepRule:
    """The keep rule of ``spec`` with its model's calibrated threshold; ValueError naming the checkpoint
    when it has none for the rule."""
    return load_segmenter(spec).keep_rule(spec.keep)


def calibration_warning(spec: SegmentationSpec) -> str | None:
    """The line to print once when ``spec``'s model is a PS checkpoint that records no calibration."""
    from playseg_core.ps.labelling import is_calibrated, uncalibrated_warning

    segmenter = load_segmenter(spec)
    if spec.method != "ps" or is_calibrated(segmenter.checkpoint_meta):
        return None
    return uncalibrated_warning(f"--segment {spec.model}")
