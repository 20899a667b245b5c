"""The square table's 8 symmetries (rotations by quarter turns, and those after a mirror), applied to
training samples: the camera frame, the state, the commanded velocity and the instruction's words.

The camera looks straight down at the centre of a square table, so turning the world a quarter turn
turns the frame a quarter turn, exactly (render.py centres the table in the frame). Blocks look the
same turned; what changes is every position and velocity, and the words that name a side: "left"
becomes "down" under a quarter turn, "the top left corner" the "bottom left corner". Each symmetry is
the matrix M = R^k F^m about the table's centre (R a quarter turn anticlockwise, F the mirror x -> -x).
A policy trained on all 8 sees 8 layouts for each recorded one, with instructions that still match.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from playseg_core.data.features import ACTION, STATE
from playseg_core.domains.tabletop.encoder import KIND as OBJECT_MAPS
from playseg_core.domains.tabletop.instructions import (
    DIRECTIONS,
    FAMILIES,
    REGION_CELLS,
    TASK_BY_TEXT,
    Task,
)
from playseg_core.domains.tabletop.spec import CAMERA, TABLE_SIZE
from playseg_core.ps.encoders import EncoderSpec

_QUARTER_TURN = np.array([[0, -1], [1, 0]])
_MIRROR = np.array([[-1, 0], [0, 1]])
SYMMETRIES: tuple[tuple[int, bool], ...] = tuple((k, m) for m in (False, True) for k in range(4))
"""(quarter turns anticlockwise, mirrored first) of each of the 8 symmetries; (0, False) is the identity."""


def symmetry_matrix(quarter_turns: int, mirror: bool) -> np.ndarray:
    """The 2x2 integer matrix of the symmetry on table vectors (x right, y up)."""
    return np.linalg.matrix_power(_QUARTER_TURN, quarter_turns) @ (
        _MIRROR if mirror else np.eye(2, dtype=int)
    )


def _direction_word(vector: np.ndarray) -> str:
    return next(word for word, unit in DIRECTIONS.items() if np.array_equal(np.asarray(unit), vector))


def _region_name(offset: np.ndarray) -> str:
    cell = (int(offset[0]) + 1, int(offset[1]) + 1)
    return next(name for name, at in REGION_CELLS.items() if at == cell)


def transformed_task(task: Task, matrix: np.ndarray) -> Task:
    """The task that says the same of the transformed table (same blocks, turned region or direction)."""
    region, direction = task.region, task.direction
    if region:
        column, row = REGION_CELLS[region]
        region = _region_name(matrix @ np.array([column - 1, row - 1]))
    if direction:
        direction = _direction_word(matrix @ np.asarray(DIRECTIONS[direction], dtype=int))
    return _TASKS[(task.family, task.block, task.other, region, direction)]


_TASKS: dict[tuple[str, int, int, str, str], Task] = {
    (t.family, t.block, t.other, t.region, t.direction): t
    for family in FAMILIES.values()
    for t in family.tasks
}


def transform_instruction(text: str, matrix: np.ndarray) -> str:
    """The instruction ``text`` for the transformed table; a text that is no tabletop instruction (a
    label from elsewhere) is returned as it is."""
    task = TASK_BY_TEXT.get(text)
    return text if task is None else transformed_task(task, matrix).text


def transform_frames(frames: np.ndarray, quarter_turns: int, mirror: bool) -> np.ndarray:
    """(N, H, W, C) top-down frames of a square view, as the transformed table would be seen."""
    if mirror:
        frames = frames[:, :, ::-1]
    return np.rot90(frames, k=quarter_turns, axes=(1, 2))


def transform_points(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """(..., 2) table positions turned about the table's centre."""
    centre = TABLE_SIZE / 2
    return (points - centre) @ matrix.T.astype(points.dtype) + centre


def random_symmetry(
    observations: dict[str, np.ndarray],
    instructions: Sequence[str],
    actions: np.ndarray,
    rng: np.random.Generator,
) -> tuple[dict[str, np.ndarray], list[str], np.ndarray]:
    """A batch of training samples (the ``bc`` policy's: observations by feature, instructions, (N, 2)
    velocity commands), each under one of the 8 symmetries drawn at random (the identity among them)."""
    chosen = rng.integers(len(SYMMETRIES), size=len(instructions))
    return apply_symmetries(observations, instructions, actions, chosen)


def apply_symmetries(
    observations: dict[str, np.ndarray],
    instructions: Sequence[str],
    actions: np.ndarray,
    chosen: np.ndarray,
) -> tuple[dict[str, np.ndarray], list[str], np.ndarray]:
    """The samples, sample i under ``SYMMETRIES[chosen[i]]``; new arrays, the inputs left as they are."""
    frames, state = observations[CAMERA].copy(), observations[STATE].copy()
    actions, instructions = np.array(actions, copy=True), list(instructions)
    for index in range(1, len(SYMMETRIES)):  # 0 is the identity
        rows = np.flatnonzero(chosen == index)
        if len(rows) == 0:
            continue
        turned = turn_clip({CAMERA: frames[rows], STATE: state[rows], ACTION: actions[rows]}, index)
        frames[rows], state[rows], actions[rows] = turned[CAMERA], turned[STATE], turned[ACTION]
        for row in rows:
            instructions[row] = turn_instruction(instructions[row], index)
    return {**observations, CAMERA: frames, STATE: state}, instructions, actions


def turn_clip(inputs: dict[str, np.ndarray], number: int) -> dict[str, np.ndarray]:
    """A training clip of Play Segmentation as recorded (the camera's frames, the states, the velocity
    commands, by feature; any of them may be absent) under ``SYMMETRIES[number]``, as new arrays; the
    domain's ``CLIP_SYMMETRIES`` with `turn_instruction`."""
    quarter_turns, mirror = SYMMETRIES[number]
    matrix = symmetry_matrix(quarter_turns, mirror)
    out = dict(inputs)
    if CAMERA in inputs:
        out[CAMERA] = np.ascontiguousarray(
            transform_frames(np.asarray(inputs[CAMERA]), quarter_turns, mirror)
        )
    if STATE in inputs:
        out[STATE] = _transform_state(np.asarray(inputs[STATE]), matrix)
    if ACTION in inputs:
        out[ACTION] = _transform_vectors(np.asarray(inputs[ACTION]), matrix)
    return out


def turn_instruction(text: str, number: int) -> str:
    """The instruction ``text`` for the table under ``SYMMETRIES[number]`` (`transform_instruction`)."""
    return transform_instruction(text, symmetry_matrix(*SYMMETRIES[number]))


def turn_block_rows(spec: EncoderSpec, rows: torch.Tensor, number: int) -> torch.Tensor | None:
    """The object-map encoder's blocks (`ObjectMapConfig` pooling "blocks": each block's image
    coordinates, x right and y down, about the frame's centre) for the frames under ``SYMMETRIES[number]``,
    from its rows of the frames as recorded: the positions turn as the table does, the blocks keep their
    order. None for any other encoder (its rows are encoded from the turned frames)."""
    if spec.kind != OBJECT_MAPS or spec.config.get("pooling") != "blocks":
        return None
    matrix = symmetry_matrix(*SYMMETRIES[number])
    flip = np.diag([1, -1])  # image y runs down, the table's up
    image_matrix = torch.as_tensor(flip @ matrix @ flip, dtype=rows.dtype)
    points = rows.reshape(rows.shape[0], -1, 2)
    return (points @ image_matrix.T).reshape(rows.shape)


def _transform_state(state: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    state = np.array(state, copy=True)
    state[:, :2] = transform_points(state[:, :2], matrix)  # spec.STATE_NAMES: x, y, vx, vy
    state[:, 2:4] = _transform_vectors(state[:, 2:4], matrix)
    return state


def _transform_vectors(vectors: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    return vectors @ matrix.T.astype(vectors.dtype)


__all__ = [
    "SYMMETRIES",
    "turn_block_rows",
    "apply_symmetries",
    "random_symmetry",
    "symmetry_matrix",
    "transform_frames",
    "transform_instruction",
    "transform_points",
    "transformed_task",
    "turn_clip",
    "turn_instruction",
]
