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
from torch.nn import functional as F

from playseg_core.data.features import Feature, FeatureError
from playseg_core.domains.tabletop.spec import COLOUR_RGB, COLOURS, EFFECTOR_RGB, SHAPES
from playseg_core.ps.encoders import (
    EncoderSpec,
    ObservationEncoder,
    cell_centres,
    cell_entities,
    register_encoder,
)

KIND = "tabletop.object_maps"


@dataclass
class ObjectMapConfig:
    # RGB distance (0-255) at which a pixel's membership falls to 0.6; the floor is 38 from the effector
    colour_sigma: float = 15.0
    patch: int = 4  # the first conv reads non-overlapping patch x patch pixel squares
    channels: int = 32
    feature_dim: int = 128
    # "grid": features of an 8x8 grid (what PS reads); "keypoints": the image coordinates of `keypoints`
    # learnt detectors (a spatial soft-argmax each); "blocks": where each block is,
    # found by colour (`ObjectMapEncoder.blobs`), as entities with what the convolutions see there
    pooling: str = "grid"
    keypoints: int = 16
    blob_iterations: int = 5  # rounds of the two-means split of each colour's pixels


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
        if cfg.pooling not in ("grid", "keypoints", "blocks") or cfg.keypoints < 1:
            raise FeatureError(
                f"{KIND}: pooling must be 'grid', 'keypoints' or 'blocks' with keypoints >= 1, got "
                f"{cfg.pooling!r} and {cfg.keypoints}"
            )
        if cfg.blob_iterations < 1:
            raise FeatureError(f"{KIND}: blob_iterations must be >= 1, got {cfg.blob_iterations}")
        self.keypoints = cfg.keypoints if cfg.pooling == "keypoints" else 0
        self.blocks = cfg.pooling == "blocks"
        self.patch, self.blob_iterations = cfg.patch, cfg.blob_iterations
        if self.keypoints or self.blocks:
            # Full patch resolution (a soft-argmax or a blob's centre is exact to a fraction of a patch);
            # a 3x3 conv lets the features tell one block from its same-coloured twin by its outline.
            layers = [
                nn.Conv2d(len(palette), cfg.channels, cfg.patch, stride=cfg.patch),
                nn.GELU(),
                nn.Conv2d(cfg.channels, cfg.channels, 3, padding=1),
                nn.GELU(),
            ]
            centres = cell_centres(height // cfg.patch, width // cfg.patch)
            self.register_buffer("cell_centres", centres, persistent=False)  # (cells, 2) x, y
            if self.keypoints:
                self.out_dim = 2 * cfg.keypoints
                self.convs = nn.Sequential(*layers, nn.Conv2d(cfg.channels, cfg.keypoints, 1))
            else:  # no detector to learn: the colours find the blocks
                self.convs = nn.Sequential(*layers)
                self.identity = nn.Parameter(torch.randn(len(COLOURS), cfg.channels) * 0.1)  # per colour
                self.entity_dim = cfg.channels
                self.out_dim = 2 * len(COLOURS) * len(SHAPES)
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
        self.entity_dim = cfg.channels

    def masks(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, colours + 1, H, W) soft membership of each palette colour."""
        rgb = frames.float() / 255.0
        # |x - p|^2 expanded: one (N, H, W, 3) x (3, K) product instead of an (N, K, H, W, 3) difference.
        distance = (
            rgb.square().sum(-1, keepdim=True) - 2 * rgb @ self.palette.T + self.palette.square().sum(-1)
        )
        return torch.exp(-distance.clamp_min(0) * self.inverse_variance).permute(0, 3, 1, 2)

    def blobs(self, mass: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, G, cells) colour mass per cell -> the centres (N, G, S, 2) of each colour's S = len(SHAPES)
        blocks and each block's share of every cell (N, G, S, cells).

        A soft two-means split of the colour's pixels (S of them; the same for any S), started at both
        ends of the pixels' main axis: the blocks of one colour differ only in shape, so where they are
        comes from the colour and which is which is left to the entity features.
        """
        total = mass.sum(-1, keepdim=True).clamp_min(1e-6)
        mean = (mass @ self.cell_centres) / total  # (N, G, 2)
        offset = self.cell_centres - mean[:, :, None]  # (N, G, cells, 2)
        cov = torch.einsum("ngc,ngci,ngcj->ngij", mass, offset, offset) / total[..., None]
        xx, xy, yy = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
        angle = 0.5 * torch.atan2(2 * xy, xx - yy)
        axis = torch.stack([torch.cos(angle), torch.sin(angle)], dim=-1)  # (N, G, 2)
        spread = (0.5 * (xx + yy) + ((0.5 * (xx - yy)) ** 2 + xy**2).sqrt()).clamp_min(1e-8).sqrt()
        ends = torch.linspace(-1.0, 1.0, len(SHAPES))[None, None, :, None]
        centres = mean[:, :, None] + ends * (spread[..., None] * axis)[:, :, None]  # (N, G, S, 2)
        for _ in range(self.blob_iterations):
            distance = (self.cell_centres - centres[..., None, :]).square().sum(-1)  # (N, G, S, cells)
            share = torch.softmax(-distance / 0.005, dim=2) * mass[:, :, None]
            centres = (share @ self.cell_centres) / share.sum(-1, keepdim=True).clamp_min(1e-6)
        return centres, share

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, feature_dim), or (N, 2 * keypoints) or (N, 2 * blocks) coordinates
        in [-1, 1]."""
        if self.keypoints or self.blocks:
            return self.encode_with_entities(frames)[0]
        return self.proj(self.convs(self.masks(frames)))  # the grid: no entities to build

    def encode_with_entities(
        self, frames: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """``forward``'s output and the entities: with the grid, its cells before the pooling (one per two
        patches); with blocks, each block where `blobs` finds them, their features what
        the convolutions see there plus a learnt embedding of the colour; with keypoints none."""
        masks = self.masks(frames)
        if self.keypoints:
            weights = torch.softmax(self.convs(masks).flatten(2), dim=-1)  # (N, K, cells)
            return (
                (weights @ self.cell_centres).flatten(1),
                None,
                None,
            )  # (N, K, 2) expected (x, y) -> (N, 2K)
        cells = self.convs[:4](masks)
        if not self.blocks:
            return self.proj(self.convs[4](cells)), *cell_entities(cells)
        # The effector is not an entity: the state says where it is, and its dark colour also matches
        # the floor's shadows.
        mass = F.avg_pool2d(masks[:, :-1], self.patch).flatten(2)  # (N, colours, cells)
        centres, share = self.blobs(mass)
        positions = centres.flatten(1, 2)  # (N, blocks, 2), colour-major
        weights = share.flatten(1, 2)
        weights = weights / weights.sum(-1, keepdim=True).clamp_min(1e-6)
        identity = self.identity.repeat_interleave(len(SHAPES), dim=0)
        entities = weights @ cells.flatten(2).transpose(1, 2) + identity
        return positions.flatten(1), entities, positions


def object_map_spec(feature: Feature, config: ObjectMapConfig | None = None) -> EncoderSpec:
    return EncoderSpec(KIND, feature.name, asdict(config or ObjectMapConfig()))


__all__ = ["KIND", "ObjectMapConfig", "ObjectMapEncoder", "object_map_spec"]
