"""What BabyAI play is, without minigrid: instructions, actions, the camera, the domain's name.

Imported by everything in this domain package (and by nothing outside it); minigrid itself is only
imported where the environment runs (play.py, evaluation.py).
"""

from __future__ import annotations

COLOURS: tuple[str, ...] = ("red", "green", "blue", "purple", "yellow", "grey")
OBJECT_TYPES: tuple[str, ...] = ("box", "ball", "key")
ARTICLES: tuple[str, ...] = ("the", "a")

INSTRUCTIONS: tuple[str, ...] = tuple(
    f"go to {article} {colour} {obj_type}"
    for article in ARTICLES
    for colour in COLOURS
    for obj_type in OBJECT_TYPES
)
"""The 36 BabyAI GoTo instructions in a fixed order: class index = position in this tuple."""

NUM_ACTIONS = 7
"""minigrid's discrete actions: left, right, forward, pickup, drop, toggle, done."""

DOMAIN = "babyai"
"""The name datasets, bags and checkpoints give this domain."""

CAMERA = "observation.images.top"
"""The one camera: the full room seen from above, rendered tile by tile."""

STEPS_PER_SECOND = 10.0
"""The step rate play bags are stamped at (BabyAI itself has no clock)."""

__all__ = [
    "ARTICLES",
    "CAMERA",
    "COLOURS",
    "DOMAIN",
    "INSTRUCTIONS",
    "NUM_ACTIONS",
    "OBJECT_TYPES",
    "STEPS_PER_SECOND",
]
