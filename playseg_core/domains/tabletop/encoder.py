"""The tabletop camera's step encoder: the frame as maps of the things on the table, then where each
block is (``blocks``), or a small CNN (``grid``, ``keypoints``).

Registered as step encoder kind ``tabletop.object_maps`` (ps/encoders.py); `step_encoders` in this package
selects its blocks, each colour's cube and cylinder told apart by size, for the tabletop camera. What it
knows of the world is only how things look (spec.py colours and sizes); it reads pixels like the generic
camera CNN and works on any frame size.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from playseg_core.data.features import Feature, FeatureError
from playseg_core.domains.tabletop.spec import (
    COLOUR_RGB,
    COLOURS,
    CUBE_SIDE,
    CYLINDER_RADIUS,
    EFFECTOR_RGB,
    SHAPES,
)
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
    # "grid": features of an 8x8 grid (what PS read before the blocks); "keypoints": the image
    # coordinates of `keypoints` learnt detectors (a spatial soft-argmax each); "blocks": where each
    # block is, found by colour (`ObjectMapEncoder.blobs`), as entities with what the convolutions see
    pooling: str = "grid"
    keypoints: int = 16
    blob_iterations: int = 5  # rounds of the two-means split of each colour's pixels
    # blocks: put each colour's blocks in SHAPES order, told apart by their spread in pixels (a cube's
    # is larger than a cylinder's); False, as checkpoints written before it read them, in either order
    twins_by_size: bool = False
    # blocks: the 16 coordinates are multiplied by this (1: image units, [-1, 1]); entities keep image units
    position_scale: float = 1.0


# the resolution spreads are measured at: larger frames are pooled to about it, smaller ones read as
# they are (at 64x64 twins get swapped twice as often)
_SPREAD_PIXELS = 96
_WINDOW = 0.2  # side of the window read around a block, a share of the frame's (a block's diagonal ~0.12)

SHAPE_SPREAD = {"cube": CUBE_SIDE**2 / 6, "cylinder": CYLINDER_RADIUS**2 / 2}
"""Mean squared distance of a shape's top face from its centre (m^2): a cube's is 14 % larger."""


@register_encoder(KIND)
class ObjectMapEncoder(ObservationEncoder):
    """Soft colour masks (one per block colour, one for the effector), then where each block is
    (``blocks``: found by colour and size, nothing learnt; convolutions give the entities' features) or
    two convolutions pooled to a grid or to keypoints.

    The masks separate the things a label names (which block, where, next to which) before anything is
    learnt, so few annotated segments suffice; learning the same from raw RGB took the generic CNN far
    more optimizer steps than a 2-core machine gives it (docs/tabletop.md). The patch conv keeps full
    resolution inside a patch; the grid keeps where things are.
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
        self.learns = not self.blocks  # the blocks' positions come from colours and sizes alone
        self.patch, self.blob_iterations = cfg.patch, cfg.blob_iterations
        if not cfg.position_scale > 0 or (cfg.position_scale != 1.0 and cfg.pooling != "blocks"):
            raise FeatureError(
                f"{KIND}: position_scale must be > 0, and other than 1 only with pooling 'blocks', got "
                f"{cfg.position_scale} with {cfg.pooling!r}"
            )
        self.position_scale = cfg.position_scale
        self.twins_by_size = self.blocks and cfg.twins_by_size
        if self.twins_by_size:
            self.spread_pool = max(1, min(height, width) // _SPREAD_PIXELS)
            rows, columns = height // self.spread_pool, width // self.spread_pool
            self.register_buffer("pixel_centres", cell_centres(rows, columns), persistent=False)
            # [-1, 1] spans the patches' centres in `blobs`, the pixels' centres here: the scale between
            pool = self.spread_pool
            scale = [(width - cfg.patch) / (width - pool), (height - cfg.patch) / (height - pool)]
            self.register_buffer("patch_to_pixel", torch.tensor(scale), persistent=False)
            self.register_buffer("pixel_extent", torch.tensor([columns - 1.0, rows - 1.0]), persistent=False)
            # (row, column) offsets of the window read around each block: _WINDOW of the frame's side
            side = min(rows, columns, math.ceil(_WINDOW * max(rows, columns)))
            offsets = torch.arange(side)
            window = torch.stack(torch.meshgrid(offsets, offsets, indexing="ij"), dim=-1).view(-1, 2)
            self.register_buffer("window", window, persistent=False)
            self.window_side = side
            # SHAPES' positions from the largest spread down: slot order once the blobs are sorted that way
            by_spread = sorted(range(len(SHAPES)), key=lambda k: -SHAPE_SPREAD[SHAPES[k]])
            self.register_buffer("shape_slots", torch.tensor(by_spread), persistent=False)
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
                # a learnt identity per colour, or per block once the twins are told apart
                identities = len(COLOURS) * (len(SHAPES) if self.twins_by_size else 1)
                self.identity = nn.Parameter(torch.randn(identities, cfg.channels) * 0.1)
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
        batch, height, width, _ = frames.shape
        rgb = frames.reshape(-1, 3) / 255.0  # a new tensor: the in-place steps below never touch frames
        # |x - p|^2 expanded: one (pixels, 3) x (3, K) product instead of a (pixels, K, 3) difference,
        # and in place (nothing here needs a gradient): this runs on every frame the models read.
        distance = torch.addmm(self.palette.square().sum(-1), rgb, self.palette.T, alpha=-2.0)
        distance.add_(rgb.square().sum(-1, keepdim=True)).clamp_(min=0)
        members = distance.mul_(-self.inverse_variance).exp_()
        return members.view(batch, height, width, -1).permute(0, 3, 1, 2)

    def blobs(self, mass: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, G, cells) colour mass per cell -> the centres (N, G, S, 2) of each colour's S = len(SHAPES)
        blocks and each block's share of every cell (N, G, S, cells).

        A soft two-means split of the colour's pixels (S of them; the same for any S), started at both
        ends of the pixels' main axis: the blocks of one colour differ only in shape, so where they are
        comes from the colour and which is which is `order_twins`' (or, without it, the entity features').
        """
        total = mass.sum(-1, keepdim=True).clamp_min(1e-6)
        mean = (mass @ self.cell_centres) / total  # (N, G, 2)
        offset = self.cell_centres - mean[:, :, None]  # (N, G, cells, 2)
        cov = torch.einsum("ngc,ngci,ngcj->ngij", mass, offset, offset) / total[..., None]
        xx, xy, yy = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
        angle = 0.5 * torch.atan2(2 * xy, xx - yy)
        axis = torch.stack([torch.cos(angle), torch.sin(angle)], dim=-1)  # (N, G, 2)
        spread = (0.5 * (xx + yy) + ((0.5 * (xx - yy)) ** 2 + xy**2).sqrt()).clamp_min(1e-8).sqrt()
        ends = torch.linspace(-1.0, 1.0, len(SHAPES), device=mass.device, dtype=mass.dtype)[
            None, None, :, None
        ]
        centres = mean[:, :, None] + ends * (spread[..., None] * axis)[:, :, None]  # (N, G, S, 2)
        cells = self.cell_centres.square().sum(-1)
        for _ in range(self.blob_iterations):
            # |c - p|^2 expanded, as in `masks`
            distance = cells - 2 * centres @ self.cell_centres.T + centres.square().sum(-1, keepdim=True)
            share = torch.softmax(-distance / 0.005, dim=2) * mass[:, :, None]
            centres = (share @ self.cell_centres) / share.sum(-1, keepdim=True).clamp_min(1e-6)
        return centres, share

    def order_twins(
        self, masks: torch.Tensor, centres: torch.Tensor, share: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``blobs``' centres and shares with each colour's blocks in SHAPES order.

        Each blob's spread (mean squared distance of its pixels from their mean) ranks it, since the
        shapes differ in size (`SHAPE_SPREAD`); a pixel belongs to the nearest centre of its colour. At
        96 pixels a side or more, not per patch: the two spreads differ by ~2 pixels^2 at 96x96, and a
        frame of 64x64 pixels swaps ~0.5 % of the pairs (twice as many as 96x96) on random layouts.
        Only a window around each centre is read: a block covers a few dozen of the frame's pixels.
        """
        mass = masks[:, :-1]  # (N, G, h, w)
        if self.spread_pool > 1:
            mass = F.avg_pool2d(mass, self.spread_pool)
        height, width = mass.shape[-2:]
        side = self.window_side
        at = centres * self.patch_to_pixel  # (N, G, S, 2) in pixel_centres' coordinates
        # the window's top-left pixel, inside the frame
        corner = (at + 1) / 2 * self.pixel_extent - side // 2
        column = corner[..., 0].round().clamp(0, width - side).long()
        row = corner[..., 1].round().clamp(0, height - side).long()
        index = (row[..., None] + self.window[:, 0]) * width + column[..., None] + self.window[:, 1]
        batch, colours, shapes, pixels = index.shape  # (N, G, S, window pixels)
        flat = mass.permute(0, 2, 3, 1).reshape(batch, height * width, colours)  # (N, pixels, G)
        images = torch.arange(batch, device=index.device)[:, None, None, None]
        inside = flat[images, index, torch.arange(colours, device=index.device)[None, :, None, None]]
        where = self.pixel_centres[index]  # (N, G, S, window pixels, 2)
        distance = (where[..., None, :] - at[:, :, None, None]).square().sum(-1)  # (.., S)
        own = torch.softmax(-distance / 0.002, dim=-1).diagonal(dim1=2, dim2=4)  # (N, G, window, S)
        weight = inside * own.transpose(2, 3)
        total = weight.sum(-1).clamp_min(1e-6)
        mean = (weight[..., None] * where).sum(-2) / total[..., None]
        spread = (weight * (where - mean[..., None, :]).square().sum(-1)).sum(-1) / total
        ranked = torch.argsort(spread, dim=-1, descending=True)  # (N, G, S): largest first
        order = torch.empty_like(ranked)
        order[..., self.shape_slots] = ranked  # slot SHAPES[k] takes the blob of that spread rank
        centres = torch.gather(centres, 2, order[..., None].expand_as(centres))
        share = torch.gather(share, 2, order[..., None].expand_as(share))
        return centres, share

    def block_positions(self, masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, colours + 1, H, W) masks -> each block's centre (N, blocks, 2), colour-major, and its share
        of every patch (N, blocks, cells). The effector is not a block: the state says where it is, and
        its dark colour also matches the floor's shadows."""
        mass = F.avg_pool2d(masks[:, :-1], self.patch).flatten(2)  # (N, colours, cells)
        centres, share = self.blobs(mass)
        if self.twins_by_size:
            centres, share = self.order_twins(masks, centres, share)
        return centres.flatten(1, 2), share.flatten(1, 2)

    @property
    def position_columns(self) -> list[tuple[int, int]]:
        return [(2 * k, 2 * k + 1) for k in range(self.out_dim // 2)] if self.blocks else []

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, feature_dim), or (N, 2 * keypoints) or (N, 2 * blocks) coordinates
        in [-1, 1]."""
        if self.blocks:  # the positions need no convolution
            return self.block_positions(self.masks(frames))[0].flatten(1) * self.position_scale
        if self.keypoints:
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
        positions, weights = self.block_positions(masks)
        weights = weights / weights.sum(-1, keepdim=True).clamp_min(1e-6)
        identity = self.identity
        if not self.twins_by_size:
            identity = identity.repeat_interleave(len(SHAPES), dim=0)
        entities = weights @ cells.flatten(2).transpose(1, 2) + identity
        return positions.flatten(1) * self.position_scale, entities, positions


def object_map_spec(feature: Feature, config: ObjectMapConfig | None = None) -> EncoderSpec:
    return EncoderSpec(KIND, feature.name, asdict(config or ObjectMapConfig()))


__all__ = ["KIND", "ObjectMapConfig", "ObjectMapEncoder", "object_map_spec"]
