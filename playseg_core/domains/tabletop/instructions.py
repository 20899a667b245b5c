"""Instruction families, their wording and the task oracle that decides completion from the table's state.

A family is one kind of task with its wording (in one place: the family's ``wording``), the tasks it
has (one per instruction string), when a task of it may be given (``applicable``: not already done,
and worth doing from here) and when it is done (``done``). ``done`` reads the scene now and the scene
when the task was given (a push in a direction is measured from where the block was).

Regions are the nine cells of a 3 x 3 grid over the table (corners, edges, centre), each shrunk by
`REGION_MARGIN`: a block is "in the top left corner" when its centre lies well inside that cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from playseg_core.domains.tabletop.sim import Scene
from playseg_core.domains.tabletop.spec import BLOCK_EXTENTS, BLOCKS, COLOURS, TABLE_SIZE
from playseg_core.errors import PlaysegError

REGION_CELLS: MappingProxyType[str, tuple[int, int]] = MappingProxyType(
    {
        "top left corner": (0, 2),
        "top edge": (1, 2),
        "top right corner": (2, 2),
        "left edge": (0, 1),
        "centre": (1, 1),
        "right edge": (2, 1),
        "bottom left corner": (0, 0),
        "bottom edge": (1, 0),
        "bottom right corner": (2, 0),
    }
)
"""Region name -> its (column, row) cell of the 3 x 3 grid, row 0 at the bottom (small y)."""
REGION_MARGIN = 0.02
"""A block (or the effector) is in a region when its centre is at least this far inside the cell (m)."""
REGION_MIN_DISTANCE = 0.05
"""A region task is given only when the block is at least this far from the region (m)."""
EFFECTOR_REGION_MIN_DISTANCE = 0.12
"""An arm-to-region task is given only when the effector is at least this far from the region (m)."""

DIRECTIONS: MappingProxyType[str, tuple[float, float]] = MappingProxyType(
    {"left": (-1.0, 0.0), "right": (1.0, 0.0), "up": (0.0, 1.0), "down": (0.0, -1.0)}
)
"""Direction word -> unit vector on the table (up = larger y = the top of the camera image)."""
PUSH_DISTANCE = 0.10
"""A push in a direction is done when the block has moved this far that way (m)."""
PUSH_ROOM = 0.04
"""...and is given only when the block has PUSH_DISTANCE plus this much room that way before the edge."""

NEXT_TO_GAP = 0.02
"""Two blocks are next to each other when the gap between them is at most this (m)."""
NEXT_TO_MIN_GAP = 0.06
"""A next-to task is given only when the blocks are at least this far apart (m)."""
SEPARATED_GAP = 0.08
"""Two blocks are separated when the gap between them is at least this (m); a separate task is given
only for blocks next to each other."""


@dataclass(frozen=True)
class Task:
    """One instruction: its family, its text and what it names (block indices into spec.BLOCKS, -1 for
    none; a region or direction name, "" for none)."""

    family: str
    text: str
    block: int = -1
    other: int = -1
    region: str = ""
    direction: str = ""


def region_box(region: str) -> tuple[float, float, float, float]:
    """(x_low, y_low, x_high, y_high) of ``region``'s cell shrunk by REGION_MARGIN."""
    if region not in REGION_CELLS:
        raise PlaysegError(f"unknown tabletop region {region!r} (expected one of {list(REGION_CELLS)})")
    column, row = REGION_CELLS[region]
    cell = TABLE_SIZE / 3
    return (
        column * cell + REGION_MARGIN,
        row * cell + REGION_MARGIN,
        (column + 1) * cell - REGION_MARGIN,
        (row + 1) * cell - REGION_MARGIN,
    )


_REGION_BOXES = {region: region_box(region) for region in REGION_CELLS}


def distance_to_region(point: tuple[float, float] | np.ndarray, region: str) -> float:
    """Distance from ``point`` to ``region``'s box (0 inside it)."""
    x0, y0, x1, y1 = _REGION_BOXES[region] if region in _REGION_BOXES else region_box(region)
    x, y = float(point[0]), float(point[1])
    return math.hypot(max(x0 - x, 0.0, x - x1), max(y0 - y, 0.0, y - y1))


def in_region(point: tuple[float, float] | np.ndarray, region: str) -> bool:
    return distance_to_region(point, region) == 0.0


def block_gap(scene: Scene, a: int, b: int) -> float:
    """The gap between blocks ``a`` and ``b``: centre distance less both half-sizes (m)."""
    (ax, ay), (bx, by) = scene.points[a], scene.points[b]
    return math.hypot(ax - bx, ay - by) - BLOCK_EXTENTS[a] - BLOCK_EXTENTS[b]


def room_towards(scene: Scene, block: int, direction: str) -> float:
    """How far ``block`` can move in ``direction`` before it touches the table's edge (m)."""
    dx, dy = DIRECTIONS[direction]
    x, y = scene.points[block]
    coordinate, sign = (x, dx) if dx else (y, dy)
    edge = TABLE_SIZE if sign > 0 else 0.0
    return abs(edge - coordinate) - BLOCK_EXTENTS[block]


class Family:
    """An instruction family: its wording, its tasks, when one may be given and when it is done."""

    name: str = ""
    wording: str = ""

    def __init__(self) -> None:
        self.tasks: tuple[Task, ...] = self._make_tasks()

    def _make_tasks(self) -> tuple[Task, ...]:
        raise NotImplementedError

    def done(self, task: Task, scene: Scene, start: Scene) -> bool:
        raise NotImplementedError

    def applicable(self, task: Task, scene: Scene) -> bool:
        """Whether ``task`` may be given in ``scene``: not done already (judged with ``scene`` as its
        start) and worth doing from here."""
        raise NotImplementedError


class BlockToRegion(Family):
    name = "block_to_region"
    wording = "push the {block} to the {region}"

    def _make_tasks(self) -> tuple[Task, ...]:
        return tuple(
            Task(self.name, self.wording.format(block=name, region=region), block=index, region=region)
            for index, name in enumerate(BLOCKS)
            for region in REGION_CELLS
        )

    def done(self, task: Task, scene: Scene, start: Scene) -> bool:
        return in_region(scene.points[task.block], task.region)

    def applicable(self, task: Task, scene: Scene) -> bool:
        return distance_to_region(scene.points[task.block], task.region) >= REGION_MIN_DISTANCE


class BlockNextToBlock(Family):
    name = "block_next_to_block"
    wording = "push the {block} next to the {other}"

    def _make_tasks(self) -> tuple[Task, ...]:
        return tuple(
            Task(self.name, self.wording.format(block=BLOCKS[a], other=BLOCKS[b]), block=a, other=b)
            for a in range(len(BLOCKS))
            for b in range(len(BLOCKS))
            if a != b
        )

    def done(self, task: Task, scene: Scene, start: Scene) -> bool:
        return block_gap(scene, task.block, task.other) <= NEXT_TO_GAP

    def applicable(self, task: Task, scene: Scene) -> bool:
        return block_gap(scene, task.block, task.other) >= NEXT_TO_MIN_GAP


class BlockInDirection(Family):
    name = "block_in_direction"
    wording = "push the {block} {direction}"

    def _make_tasks(self) -> tuple[Task, ...]:
        return tuple(
            Task(self.name, self.wording.format(block=name, direction=word), block=index, direction=word)
            for index, name in enumerate(BLOCKS)
            for word in DIRECTIONS
        )

    def done(self, task: Task, scene: Scene, start: Scene) -> bool:
        (x, y), (x0, y0) = scene.points[task.block], start.points[task.block]
        dx, dy = DIRECTIONS[task.direction]
        return (x - x0) * dx + (y - y0) * dy >= PUSH_DISTANCE

    def applicable(self, task: Task, scene: Scene) -> bool:
        return room_towards(scene, task.block, task.direction) >= PUSH_DISTANCE + PUSH_ROOM


class SeparateBlocks(Family):
    name = "separate_blocks"
    wording = "separate the {block} from the {other}"

    def _make_tasks(self) -> tuple[Task, ...]:
        # One task per pair, named in BLOCKS order: "separate" is symmetric.
        return tuple(
            Task(self.name, self.wording.format(block=BLOCKS[a], other=BLOCKS[b]), block=a, other=b)
            for a in range(len(BLOCKS))
            for b in range(a + 1, len(BLOCKS))
        )

    def done(self, task: Task, scene: Scene, start: Scene) -> bool:
        return block_gap(scene, task.block, task.other) >= SEPARATED_GAP

    def applicable(self, task: Task, scene: Scene) -> bool:
        return block_gap(scene, task.block, task.other) <= NEXT_TO_GAP


class EffectorToRegion(Family):
    name = "effector_to_region"
    wording = "move the arm to the {region}"

    def _make_tasks(self) -> tuple[Task, ...]:
        return tuple(
            Task(self.name, self.wording.format(region=region), region=region) for region in REGION_CELLS
        )

    def done(self, task: Task, scene: Scene, start: Scene) -> bool:
        return in_region(scene.effector_point, task.region)

    def applicable(self, task: Task, scene: Scene) -> bool:
        return distance_to_region(scene.effector_point, task.region) >= EFFECTOR_REGION_MIN_DISTANCE


FAMILIES: MappingProxyType[str, Family] = MappingProxyType(
    {
        family.name: family
        for family in (
            BlockToRegion(),
            BlockNextToBlock(),
            BlockInDirection(),
            SeparateBlocks(),
            EffectorToRegion(),
        )
    }
)
"""Every instruction family by name."""

TASKS: tuple[Task, ...] = tuple(task for family in FAMILIES.values() for task in family.tasks)
INSTRUCTIONS: tuple[str, ...] = tuple(task.text for task in TASKS)
"""Every instruction string in a fixed order: a dataset's instruction index is the position here."""
TASK_BY_TEXT: MappingProxyType[str, Task] = MappingProxyType({task.text: task for task in TASKS})


CALVIN_INSTRUCTIONS: tuple[str, ...] = (
    *(f"push the {colour} cube {direction}" for colour in COLOURS for direction in DIRECTIONS),
    *(f"push the {colour} cylinder to the centre" for colour in COLOURS),
    *(f"push the {colour} cube next to the {colour} cylinder" for colour in COLOURS),
    *(f"move the arm to the {region}" for region in REGION_CELLS if region != "centre"),
)
"""The `calvin` task set: 32 task types, each a distinct skill with one wording, as CALVIN's 34 (push a
cube one way, a cylinder to the centre, a cube next to its twin cylinder, the arm to a corner or an
edge). Closed under the table's 8 symmetries (symmetry.py): a turned instruction is one of the set."""


@dataclass(frozen=True)
class TaskSet:
    """The instructions play may give, and how the next one is drawn: ``by_family`` first draws a family
    uniformly among those with a task that may be given, then one of its tasks (each family as often
    whatever its size); otherwise one of the tasks that may be given, uniformly (each task type about
    as often)."""

    name: str
    tasks: tuple[Task, ...]
    by_family: bool

    @property
    def instructions(self) -> tuple[str, ...]:
        """The set's instruction strings: a dataset's instruction index is the position here."""
        return tuple(task.text for task in self.tasks)

    @property
    def members(self) -> frozenset[Task] | None:
        """The set's tasks to draw among (None: every task)."""
        return None if self.tasks == TASKS else frozenset(self.tasks)


def task_for(text: str) -> Task:
    """The task of instruction ``text``; ValueError naming it when there is none."""
    if text not in TASK_BY_TEXT:
        raise PlaysegError(f"unknown tabletop instruction {text!r}")
    return TASK_BY_TEXT[text]


def is_done(task: Task, scene: Scene, start: Scene) -> bool:
    """The task oracle: whether ``task``, given in ``start``, is done in ``scene``."""
    return FAMILIES[task.family].done(task, scene, start)


def applicable_tasks(scene: Scene, among: frozenset[Task] | None = None) -> dict[str, list[Task]]:
    """Family name -> the tasks (of ``among``, or any) that may be given in ``scene`` (families without
    any left out), in family and task order."""
    by_family: dict[str, list[Task]] = {}
    for name, family in FAMILIES.items():
        tasks = [
            task
            for task in family.tasks
            if (among is None or task in among) and family.applicable(task, scene)
        ]
        if tasks:
            by_family[name] = tasks
    return by_family


TASK_SETS: MappingProxyType[str, TaskSet] = MappingProxyType(
    {
        "all": TaskSet("all", TASKS, by_family=True),
        "calvin": TaskSet("calvin", tuple(task_for(text) for text in CALVIN_INSTRUCTIONS), by_family=False),
    }
)
"""Task sets by name (`PlayConfig.task_set`): ``all``, the 197 instructions of the five families, and
``calvin``, CALVIN's shape (`CALVIN_INSTRUCTIONS`)."""


def task_set(name: str) -> TaskSet:
    """The task set ``name``; ValueError naming it and the known ones."""
    if name not in TASK_SETS:
        raise PlaysegError(f"unknown tabletop task set {name!r} (expected one of {', '.join(TASK_SETS)})")
    return TASK_SETS[name]


__all__ = [
    "CALVIN_INSTRUCTIONS",
    "TASK_SETS",
    "TaskSet",
    "task_set",
    "DIRECTIONS",
    "FAMILIES",
    "INSTRUCTIONS",
    "REGION_CELLS",
    "TASKS",
    "Family",
    "Task",
    "applicable_tasks",
    "block_gap",
    "distance_to_region",
    "in_region",
    "is_done",
    "region_box",
    "room_towards",
    "task_for",
]
