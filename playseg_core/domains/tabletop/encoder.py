"""The tabletop camera's step encoder: the frame as maps of the things on the table, then a small CNN.

Registered as step encoder kind ``tabletop.object_maps`` (ps/encoders.py); `step_encoders` in this package
selects it for the tabletop camera. What it knows of the world is only how things look (spec.py and
render.py colours); it reads pixels like the generic camera CNN and works on any frame size.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

from playseg_core.data.features import Feature, FeatureError
from playseg_core.domains.tabletop.spec import COLOUR_RGB, COLOURS, EFFECTOR_RGB
from playseg_core.ps.encoders import EncoderSpec, ObservationEncoder, register_encoder

KIND = "tabletop.object_maps"


@dataclass
class ObjectMapConfig:
    # RGB distance (0-255) at which a pixel's membership falls to 0.6; the floor is 38 from the effector
    colour_sigma: float = 15.0
    patch: int = 4  # the first conv reads non-overlapping patch x patch pixel squares
    channels: int = 32
    feature_dim: int = 128
    # "grid": features of an 8x8 grid (what PS reads); "keypoints": the image coordinates of `keypoints`
    # learnt detectors (a spatial soft-argmax each), what the policy reads
    pooling: str = "grid"
    keypoints: int = 16


@register_encoder(KIND)
class ObjectMapEncoder(ObservationEncoder):
    """Soft colour masks (one per block colour, one for the effector), then two convolutions.

    The masks separate the things a label names (which block, where, next to which) before anything is
    learnt, so few annotated segments suffice; learning the same from raw RGB took the generic CNN far
    more optimizer steps than a 2-core machine gives it (docs/tabletop.md). The patch conv keeps full
    resolution inside a patch, which is what tells a cube's corners from a cylinder's round edge; the
    final grid keeps where things are.
    """

    def __init__(self, feature: Feature, config: dict[str, Any]) -> None:
        super().__init__(feature)
        cfg = ObjectMapConfig(**config)
        height, width, depth = feature.shape
        if depth != 3 or height < 4 * cfg.patch or width < 4 * cfg.patch:
            raise FeatureError(
                f"{KIND}: feature {feature.name!r} must be an RGB frame of at least "
                f"{4 * cfg.patch}x{4 * cfg.patch} pixels, got shape {tuple(feature.shape)}"
            )
        palette = [COLOUR_RGB[colour] for colour in COLOURS] + [EFFECTOR_RGB]
        self.register_buffer("palette", torch.tensor(palette, dtype=torch.float32) / 255.0, persistent=False)
        self.inverse_variance = (255.0 / cfg.colour_sigma) ** 2 / 2.0
        if cfg.pooling not in ("grid", "keypoints") or cfg.keypoints < 1:
            raise FeatureError(
                f"{KIND}: pooling must be 'grid' or 'keypoints' with keypoints >= 1, got {cfg.pooling!r} "
                f"and {cfg.keypoints}"
            )
        self.keypoints = cfg.keypoints if cfg.pooling == "keypoints" else 0
        if self.keypoints:
            # Full patch resolution (the soft-argmax is exact to a fraction of a patch); a 3x3 conv lets
            # a detector tell one block from its same-coloured twin by its outline.
            self.out_dim = 2 * cfg.keypoints
            self.convs = nn.Sequential(
                nn.Conv2d(len(palette), cfg.channels, cfg.patch, stride=cfg.patch),
                nn.GELU(),
                nn.Conv2d(cfg.channels, cfg.channels, 3, padding=1),
                nn.GELU(),
                nn.Conv2d(cfg.channels, cfg.keypoints, 1),
            )
            rows, columns = height // cfg.patch, width // cfg.patch
            grid_y, grid_x = torch.meshgrid(
                torch.linspace(-1.0, 1.0, rows), torch.linspace(-1.0, 1.0, columns), indexing="ij"
            )
            self.register_buffer("grid", torch.stack([grid_x, grid_y]).reshape(2, -1), persistent=False)
            return
        self.out_dim = cfg.feature_dim
        self.convs = nn.Sequential(
            nn.Conv2d(len(palette), cfg.channels, cfg.patch, stride=cfg.patch),
            nn.GELU(),
            nn.Conv2d(cfg.channels, cfg.channels, 3, stride=2, padding=1),
            nn.GELU(),
            nn.AdaptiveAvgPool2d(8),
        )
        self.proj = nn.Sequential(nn.Flatten(), nn.Linear(cfg.channels * 64, cfg.feature_dim), nn.GELU())

    def masks(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, colours + 1, H, W) soft membership of each palette colour."""
        rgb = frames.float() / 255.0
        # |x - p|^2 expanded: one (N, H, W, 3) x (3, K) product instead of an (N, K, H, W, 3) difference.
        distance = (
            rgb.square().sum(-1, keepdim=True) - 2 * rgb @ self.palette.T + self.palette.square().sum(-1)
        )
        return torch.exp(-distance.clamp_min(0) * self.inverse_variance).permute(0, 3, 1, 2)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, feature_dim), or (N, 2 * keypoints) coordinates in [-1, 1]."""
        if self.keypoints:
            weights = torch.softmax(self.convs(self.masks(frames)).flatten(2), dim=-1)  # (N, K, cells)
            return (weights @ self.grid.T).flatten(1)  # (N, K, 2) expected (x, y) -> (N, 2K)
        return self.proj(self.convs(self.masks(frames)))


def object_map_spec(feature: Feature, config: ObjectMapConfig | None = None) -> EncoderSpec:
    return EncoderSpec(KIND, feature.name, asdict(config or ObjectMapConfig()))


__all__ = ["KIND", "ObjectMapConfig", "ObjectMapEncoder", "object_map_spec"]
