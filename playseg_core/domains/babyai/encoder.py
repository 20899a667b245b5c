"""The BabyAI grid-tile step encoder: a camera frame rendered tile by tile -> what the agent faces.

Registered as step encoder kind ``babyai.grid_tiles`` (ps/encoders.py); `image_encoder` in this package
selects it for BabyAI's camera.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from playseg_core.data.features import Feature, FeatureError
from playseg_core.ps.encoders import EncoderSpec, ObservationEncoder, register_encoder

KIND = "babyai.grid_tiles"


@dataclass
class GridTileConfig:
    tile_size: int = 8  # BabyAI renders a grid of 8x8-pixel tiles: the first conv reads one tile
    tile_channels: int = 64
    object_dim: int = 32  # per-tile "what is here" embedding
    look_heads: int = 2  # attention maps over tiles ("the tile the agent faces", ...)
    feature_dim: int = 128


@register_encoder(KIND)
class GridTileEncoder(ObservationEncoder):
    """Per-frame CNN over the tile grid; translation-equivariant up to attention and sum pooling.

    The tile conv (kernel = stride = tile size) embeds each tile (object type and colour, the agent and
    its direction). Two per-tile maps come from it: `what` (the tile's content) and `look` (a 3x3 conv:
    "this tile is in front of the agent", from the neighbouring agent tile and its direction). Softmax
    attention of `look` over the tiles reads out the content of the faced tile; the product of that with
    the summed contents counts how many tiles hold the same thing (the article "the" vs "a"). Nothing
    depends on where things are, so the model cannot memorise room layouts, and "what is faced" is a
    product of where and what, so it holds for objects never faced in training.
    """

    def __init__(self, feature: Feature, config: dict[str, Any]) -> None:
        super().__init__(feature)
        cfg = GridTileConfig(**config)
        height, width, _ = feature.shape
        if height % cfg.tile_size or width % cfg.tile_size:
            raise FeatureError(
                f"{KIND}: feature {feature.name!r} is {height}x{width}, not a grid of {cfg.tile_size}-pixel tiles"
            )
        self.out_dim = cfg.feature_dim
        self.tile = nn.Conv2d(3, cfg.tile_channels, cfg.tile_size, stride=cfg.tile_size)
        self.tile_mix = nn.Conv2d(cfg.tile_channels, cfg.tile_channels, 1)
        self.what = nn.Conv2d(cfg.tile_channels, cfg.object_dim, 1)
        self.look = nn.Conv2d(cfg.tile_channels, cfg.look_heads, 3, padding=1)
        self.what_norm = nn.LayerNorm(cfg.object_dim)
        # Per head: how sharply "looks like the faced tile" falls off with the embedding distance.
        self.log_sharpness = nn.Parameter(torch.full((cfg.look_heads,), 2.0))
        faced_dim = cfg.look_heads * cfg.object_dim
        self.proj = nn.Sequential(
            nn.Linear(faced_dim + cfg.look_heads, cfg.feature_dim),
            nn.GELU(),
            nn.Linear(cfg.feature_dim, cfg.feature_dim),
        )

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, H, W, 3) uint8 -> (N, feature_dim)."""
        x = frames.permute(0, 3, 1, 2).float() / 255.0
        tiles = F.relu(self.tile_mix(F.relu(self.tile(x))))
        what = self.what_norm(self.what(tiles).flatten(2).transpose(1, 2))  # (N, tiles, object_dim)
        look = torch.softmax(self.look(tiles).flatten(2), dim=-1)  # (N, heads, tiles)
        faced = look @ what  # (N, heads, object_dim)
        # Identical tiles have identical embeddings: count the tiles that look like the faced one.
        distance = (what[:, None] - faced[:, :, None]).square().mean(-1)  # (N, heads, tiles)
        count = torch.exp(-distance * self.log_sharpness.exp()[:, None]).sum(-1)
        return self.proj(torch.cat([faced.flatten(1), count], dim=1))


def grid_tile_spec(feature: Feature, config: GridTileConfig | None = None) -> EncoderSpec:
    return EncoderSpec(KIND, feature.name, asdict(config or GridTileConfig()))


def frames_are_tiled(shape: tuple[int, ...], tile_size: int = GridTileConfig.tile_size) -> bool:
    return len(shape) == 3 and shape[0] % tile_size == 0 and shape[1] % tile_size == 0 and shape[0] > 0


__all__ = ["KIND", "GridTileConfig", "GridTileEncoder", "frames_are_tiled", "grid_tile_spec"]
