"""The top-down camera: an RGB frame of the table drawn with OpenCV into a numpy array (no display, no
OpenGL).

The view is the table plus a border wide enough to show the effector anywhere within its reach; image
rows run from the table's top edge (largest y) down. Shapes are drawn with sub-pixel precision and
anti-aliased edges, so a block moving by less than a pixel still changes the frame.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from playseg_core.domains.tabletop.sim import Scene
from playseg_core.domains.tabletop.spec import (
    BLOCKS,
    COLOUR_RGB,
    CUBE_SIDE,
    CYLINDER_RADIUS,
    DEFAULT_IMAGE_SIZE,
    EFFECTOR_RADIUS,
    EFFECTOR_REACH,
    EFFECTOR_RGB,
    TABLE_SIZE,
)
from playseg_core.errors import PlaysegError

VIEW_BORDER = EFFECTOR_REACH + EFFECTOR_RADIUS + 0.002
"""Width of the floor shown around the table (m): the effector stays in view at the edge of its reach."""

FLOOR_RGB = (60, 60, 66)
TABLE_RGB = (205, 200, 190)

_SHIFT = 4  # OpenCV fixed-point bits: coordinates in 1/16 pixel
_ONE = 1 << _SHIFT
_MIN_SIZE = 16


class Renderer:
    """Draws scenes as ``(size, size, 3)`` uint8 RGB frames."""

    def __init__(self, size: int = DEFAULT_IMAGE_SIZE) -> None:
        if not isinstance(size, int) or isinstance(size, bool) or size < _MIN_SIZE:
            raise PlaysegError(f"tabletop image size must be an integer >= {_MIN_SIZE} pixels, got {size!r}")
        self.size = size
        self.pixels_per_metre = size / (TABLE_SIZE + 2 * VIEW_BORDER)
        self._background = np.empty((size, size, 3), np.uint8)
        self._background[:] = FLOOR_RGB
        top_left = self._to_fixed(np.array([[0.0, TABLE_SIZE]]))[0]
        bottom_right = self._to_fixed(np.array([[TABLE_SIZE, 0.0]]))[0]
        cv2.rectangle(
            self._background, tuple(top_left), tuple(bottom_right), TABLE_RGB, -1, cv2.LINE_AA, _SHIFT
        )
        half = CUBE_SIDE / 2
        self._cube_corners = ((-half, -half), (half, -half), (half, half), (-half, half))
        self._is_cube = [name.endswith("cube") for name in BLOCKS]
        self._colours = [COLOUR_RGB[name.split()[0]] for name in BLOCKS]
        self._cylinder_radius = round(CYLINDER_RADIUS * self.pixels_per_metre * _ONE)
        self._effector_radius = round(EFFECTOR_RADIUS * self.pixels_per_metre * _ONE)

    def _to_fixed(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) table points (m) -> (N, 2) int32 pixel coordinates (column, row) in 1/16 pixel."""
        column = (points[:, 0] + VIEW_BORDER) * self.pixels_per_metre
        row = (TABLE_SIZE + VIEW_BORDER - points[:, 1]) * self.pixels_per_metre
        # -0.5: pixel centres lie at integer coordinates in OpenCV.
        return np.round((np.stack([column, row], axis=1) - 0.5) * _ONE).astype(np.int32)

    def render(self, scene: Scene) -> np.ndarray:
        """The camera frame of ``scene``, a new (size, size, 3) uint8 RGB array."""
        # Plain float arithmetic: a handful of points per frame, where numpy's per-call cost would dominate.
        scale = self.pixels_per_metre * _ONE
        offset_x = (VIEW_BORDER * self.pixels_per_metre - 0.5) * _ONE
        offset_y = ((TABLE_SIZE + VIEW_BORDER) * self.pixels_per_metre - 0.5) * _ONE
        frame = self._background.copy()
        blocks, angles = scene.blocks.tolist(), scene.angles.tolist()
        for index, (x, y) in enumerate(blocks):
            colour = self._colours[index]
            if self._is_cube[index]:
                c, s = math.cos(angles[index]), math.sin(angles[index])
                corners = [
                    (
                        round(offset_x + (x + c * dx - s * dy) * scale),
                        round(offset_y - (y + s * dx + c * dy) * scale),
                    )
                    for dx, dy in self._cube_corners
                ]
                cv2.fillConvexPoly(frame, np.array(corners, np.int32), colour, cv2.LINE_AA, _SHIFT)
            else:
                centre = (round(offset_x + x * scale), round(offset_y - y * scale))
                cv2.circle(frame, centre, self._cylinder_radius, colour, -1, cv2.LINE_AA, _SHIFT)
        ex, ey = scene.effector.tolist()
        effector = (round(offset_x + ex * scale), round(offset_y - ey * scale))
        cv2.circle(frame, effector, self._effector_radius, EFFECTOR_RGB, -1, cv2.LINE_AA, _SHIFT)
        return frame


__all__ = ["VIEW_BORDER", "Renderer"]
