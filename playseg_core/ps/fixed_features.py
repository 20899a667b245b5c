"""The outputs of step encoders that learn nothing, encoded once per episode and symmetry for training.

Such an encoder (`StepEncoder.learns` False: a camera read as object positions found by colour, say) gives
the same row for the same observation at every optimizer step, while training reads each annotated step
in many batches. Encoding it once per (episode, symmetry) and gathering rows by index removes its cost
from every step after the first; a learnt encoder is untouched and still runs in every batch.
"""

from __future__ import annotations

import numpy as np
import torch

from playseg_core.data.episode import Episode
from playseg_core.errors import PlaysegError
from playseg_core.ps.encoders import ObservationEncoder, StepEncoders
from playseg_core.ps.symmetries import ClipSymmetries

ENCODE_ROWS = 256  # observation rows per encoder pass when filling the cache


class FixedFeatureCache:
    """Rows of the fixed observation encoders' outputs, by (episode, symmetry index), filled on first use.

    Valid while the encoders are those of one model: nothing they compute changes with training.
    """

    def __init__(self, encoders: StepEncoders) -> None:
        self.encoders = encoders
        self.fixed: dict[str, ObservationEncoder] = {
            spec.feature: encoder
            for spec, encoder in zip(encoders.specs, encoders.encoders, strict=True)
            if isinstance(encoder, ObservationEncoder) and not encoder.learns
        }
        self.specs = {spec.feature: spec for spec in encoders.specs if spec.feature in self.fixed}
        # keyed by the episode object (held here, so its id stays its own): two episodes may share an id
        self._rows: dict[tuple[int, int], tuple[Episode, dict[str, torch.Tensor]]] = {}

    @property
    def features(self) -> list[str]:
        """The features whose rows come from the cache."""
        return list(self.fixed)

    def __len__(self) -> int:
        """Episode-symmetry pairs encoded so far."""
        return len(self._rows)

    def clip_rows(
        self,
        episode: Episode,
        first: int,
        last: int,
        symmetry: int = 0,
        symmetries: ClipSymmetries | None = None,
    ) -> dict[str, torch.Tensor]:
        """Each fixed feature's encoder output rows for o_first..o_last of ``episode`` turned by
        ``symmetries``' symmetry number ``symmetry`` (0: as recorded)."""
        key = (id(episode), symmetry)
        if key not in self._rows:
            self._rows[key] = (episode, self._encode(episode, symmetry, symmetries))
        return {feature: rows[first : last + 1] for feature, rows in self._rows[key][1].items()}

    @torch.no_grad()
    def _encode(
        self, episode: Episode, symmetry: int, symmetries: ClipSymmetries | None
    ) -> dict[str, torch.Tensor]:
        if symmetry and symmetries is None:
            raise PlaysegError(f"symmetry {symmetry} asked of the cache without the symmetries")
        turned: dict[str, torch.Tensor] = {}
        if symmetry and symmetries.turn_encoded is not None:  # turn the recorded rows where the domain can
            recorded_rows = self.clip_rows(episode, 0, episode.num_steps)
            for feature, spec in self.specs.items():
                rows = symmetries.turn_encoded(spec, recorded_rows[feature], symmetry)
                if rows is not None:
                    turned[feature] = rows
        if len(turned) == len(self.fixed):
            return turned
        parts: dict[str, list[torch.Tensor]] = {
            feature: [] for feature in self.fixed if feature not in turned
        }
        for first in range(0, episode.num_steps + 1, ENCODE_ROWS):  # a chunk in memory at a time
            last = min(first + ENCODE_ROWS, episode.num_steps + 1) - 1
            recorded = self.encoders.recorded_clip(episode, first, last, self.features)
            if symmetry:
                recorded = symmetries.turn_clip(recorded, symmetry)
            for feature in parts:
                encoder = self.fixed[feature]
                rows = torch.from_numpy(np.array(recorded[feature])).to(_device_of(encoder))
                parts[feature].append(encoder(rows).cpu())  # batches carry CPU rows to any device
        return {**turned, **{feature: torch.cat(chunks) for feature, chunks in parts.items()}}


def _device_of(module: torch.nn.Module) -> torch.device:
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")


__all__ = ["ENCODE_ROWS", "FixedFeatureCache"]
