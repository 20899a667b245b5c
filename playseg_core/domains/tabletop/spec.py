"""What the tabletop world is, without the physics: the table, the blocks, the end effector, the rates,
the action and state the dataset declares, the camera.

Units are metres, seconds and radians. The table is the square [0, TABLE_SIZE]^2 seen from above, x to
the right and y up (up in the camera image). Imported by every module of this package and by nothing
outside it.
"""

from __future__ import annotations

DOMAIN = "tabletop"
"""The name datasets, bags and checkpoints give this domain."""

CAMERA = "observation.images.top"
"""The one camera: the whole table seen from straight above."""

DEFAULT_IMAGE_SIZE = 96
"""Side of the square camera frame in pixels (configurable per dataset, `PlayConfig.image_size`)."""

TABLE_SIZE = 0.5
"""Side of the square table (m). Rims along its edges keep the blocks on it."""

COLOURS: tuple[str, ...] = ("red", "blue", "green", "yellow")
SHAPES: tuple[str, ...] = ("cube", "cylinder")
BLOCKS: tuple[str, ...] = tuple(f"{colour} {shape}" for shape in SHAPES for colour in COLOURS)
"""The 8 blocks, 4 colours x 2 shapes as in Language-Table; a block's index is its position here."""

COLOUR_RGB: dict[str, tuple[int, int, int]] = {
    "red": (220, 40, 40),
    "blue": (40, 80, 220),
    "green": (30, 170, 60),
    "yellow": (240, 200, 20),
}

CUBE_SIDE = 0.05
CYLINDER_RADIUS = 0.027
BLOCK_EXTENTS: tuple[float, ...] = tuple(
    CUBE_SIDE / 2 if shape == "cube" else CYLINDER_RADIUS for shape in SHAPES for _ in COLOURS
)
"""Half-size of each block (a cube's half side, a cylinder's radius): what "gap between blocks" means."""
BLOCK_MASS = 0.1  # kg
BLOCK_FRICTION = 0.5
"""Coulomb friction coefficient between a block and the table: a block stops soon after a push ends."""

EFFECTOR_RADIUS = 0.018
EFFECTOR_RGB: tuple[int, int, int] = (40, 40, 40)
"""How the camera sees the effector (render.py); the blocks' colours are COLOUR_RGB."""
EFFECTOR_REACH = 0.03
"""How far past the table's edge the effector's centre may go (it reaches over the rims, which stop only
blocks), so it can get behind a block lying against a rim."""

CONTROL_HZ = 10.0
"""Actions per second: the dataset's step rate (CALVIN's and Language-Table's teleoperation rate)."""
PHYSICS_SUBSTEPS = 10
"""Physics steps per control step (dt = 0.01 s)."""
EFFECTOR_TIME_CONSTANT = 0.05
"""The effector's velocity follows the command as a first-order lag with this time constant (s), sampled
at the control rate (86% of a change per step), so the measured velocity in the state is not a copy of
the command."""

MAX_SPEED = 0.2
"""Bound of each commanded velocity component (m/s); commands outside [-MAX_SPEED, MAX_SPEED] are clipped."""
ACTION_LOW: tuple[float, float] = (-MAX_SPEED, -MAX_SPEED)
ACTION_HIGH: tuple[float, float] = (MAX_SPEED, MAX_SPEED)
ACTION_NAMES: tuple[str, str] = ("velocity_x", "velocity_y")
"""The action: the end effector's commanded planar velocity (m/s), x right, y up."""

STATE_NAMES: tuple[str, ...] = ("effector_x", "effector_y", "effector_velocity_x", "effector_velocity_y")
"""The proprioceptive state: the effector's position (m) and measured velocity (m/s)."""

EVAL_STEP_BUDGET = 120
"""Control steps (12 s) a policy has to complete a task in the simulator evaluation (evaluation.py):
success = the task oracle says done within them. The teleoperator's own limit (`PlayConfig.max_task_steps`):
it needs 42 steps at the median, 87 at the 95th percentile."""

__all__ = [
    "ACTION_HIGH",
    "ACTION_LOW",
    "ACTION_NAMES",
    "BLOCKS",
    "BLOCK_EXTENTS",
    "BLOCK_FRICTION",
    "BLOCK_MASS",
    "CAMERA",
    "COLOURS",
    "COLOUR_RGB",
    "CONTROL_HZ",
    "CUBE_SIDE",
    "CYLINDER_RADIUS",
    "DEFAULT_IMAGE_SIZE",
    "DOMAIN",
    "EFFECTOR_RADIUS",
    "EFFECTOR_REACH",
    "EFFECTOR_RGB",
    "EFFECTOR_TIME_CONSTANT",
    "EVAL_STEP_BUDGET",
    "MAX_SPEED",
    "PHYSICS_SUBSTEPS",
    "SHAPES",
    "STATE_NAMES",
    "TABLE_SIZE",
]
