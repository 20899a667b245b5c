"""The tabletop task oracle, family by family: constructed scenes that do and do not satisfy a task."""

from __future__ import annotations

import string

import numpy as np
import pytest

from playseg_core.domains.tabletop.instructions import (
    FAMILIES,
    INSTRUCTIONS,
    NEXT_TO_GAP,
    PUSH_DISTANCE,
    REGION_CELLS,
    SEPARATED_GAP,
    TASKS,
    applicable_tasks,
    is_done,
    region_box,
    task_for,
)
from playseg_core.domains.tabletop.sim import Scene, TabletopSim
from playseg_core.domains.tabletop.spec import BLOCK_EXTENTS, BLOCKS, TABLE_SIZE

RED_CUBE, RED_CYLINDER = BLOCKS.index("red cube"), BLOCKS.index("red cylinder")
SPREAD = np.array([[0.08 + 0.11 * (i % 4), 0.14 + 0.22 * (i // 4)] for i in range(8)])
"""A layout with every block well apart from the others."""


def scene(moves: dict[int, tuple[float, float]] | None = None, effector=(0.25, 0.02)) -> Scene:
    blocks = SPREAD.copy()
    for index, position in (moves or {}).items():
        blocks[index] = position
    return Scene(blocks, np.zeros(8), np.array(effector, float), np.zeros(2))


def centre_of(region: str) -> tuple[float, float]:
    x0, y0, x1, y1 = region_box(region)
    return ((x0 + x1) / 2, (y0 + y1) / 2)


def beside(block: int, other: int, gap: float, at=(0.25, 0.25)) -> dict[int, tuple[float, float]]:
    """``block`` at ``at`` and ``other`` to its right with ``gap`` between them."""
    distance = BLOCK_EXTENTS[block] + BLOCK_EXTENTS[other] + gap
    return {block: at, other: (at[0] + distance, at[1])}


def test_instructions_are_many_distinct_and_worded_by_their_family() -> None:
    assert len(INSTRUCTIONS) >= 30 and len(set(INSTRUCTIONS)) == len(INSTRUCTIONS)
    for task in TASKS:
        family = FAMILIES[task.family]
        fields = [name for _, name, _, _ in string.Formatter().parse(family.wording) if name]
        values = {
            "block": BLOCKS[task.block] if task.block >= 0 else None,
            "other": BLOCKS[task.other] if task.other >= 0 else None,
            "region": task.region,
            "direction": task.direction,
        }
        assert task.text == family.wording.format(**{name: values[name] for name in fields})
        assert task_for(task.text) is task


def test_unknown_names_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match="unknown tabletop instruction 'fly to the moon'"):
        task_for("fly to the moon")
    with pytest.raises(ValueError, match="unknown tabletop region 'ceiling'"):
        region_box("ceiling")


@pytest.mark.parametrize("region", list(REGION_CELLS))
def test_block_to_region(region: str) -> None:
    task = task_for(f"push the red cube to the {region}")
    inside = scene({RED_CUBE: centre_of(region)})
    assert is_done(task, inside, inside)
    others = [r for r in REGION_CELLS if r != region]
    assert not any(is_done(task_for(f"push the red cube to the {r}"), inside, inside) for r in others)
    # On the cell's border (less than the margin inside): not yet.
    x0, y0, _, _ = region_box(region)
    border = scene({RED_CUBE: (x0 - 0.005, centre_of(region)[1])})
    assert not is_done(task, border, border)


def test_block_next_to_block() -> None:
    task = task_for("push the red cube next to the red cylinder")
    near = scene(beside(RED_CUBE, RED_CYLINDER, NEXT_TO_GAP - 0.005))
    apart = scene(beside(RED_CUBE, RED_CYLINDER, NEXT_TO_GAP + 0.02))
    assert is_done(task, near, apart) and not is_done(task, apart, apart)
    assert not FAMILIES[task.family].applicable(task, near)


def test_block_in_direction_is_measured_from_the_start() -> None:
    start = scene({RED_CUBE: (0.25, 0.25)})
    moved = scene({RED_CUBE: (0.25 - PUSH_DISTANCE - 0.005, 0.27)})
    short = scene({RED_CUBE: (0.25 - PUSH_DISTANCE + 0.01, 0.25)})
    assert is_done(task_for("push the red cube left"), moved, start)
    assert not is_done(task_for("push the red cube left"), short, start)
    assert not is_done(task_for("push the red cube right"), moved, start)
    assert not is_done(task_for("push the red cube up"), moved, start)
    # Done relative to its start, not to the table: the same place is not done from itself.
    assert not is_done(task_for("push the red cube left"), moved, moved)
    # No room left towards the edge: not given.
    at_edge = scene({RED_CUBE: (0.06, 0.25)})
    assert not FAMILIES["block_in_direction"].applicable(task_for("push the red cube left"), at_edge)


def test_separate_blocks() -> None:
    task = task_for("separate the red cube from the red cylinder")
    together = scene(beside(RED_CUBE, RED_CYLINDER, 0.005))
    apart = scene(beside(RED_CUBE, RED_CYLINDER, SEPARATED_GAP + 0.005))
    halfway = scene(beside(RED_CUBE, RED_CYLINDER, SEPARATED_GAP - 0.02))
    assert is_done(task, apart, together) and not is_done(task, halfway, together)
    family = FAMILIES[task.family]
    assert family.applicable(task, together) and not family.applicable(task, halfway)


def test_effector_to_region() -> None:
    task = task_for("move the arm to the bottom right corner")
    there = scene(effector=centre_of("bottom right corner"))
    elsewhere = scene(effector=centre_of("top left corner"))
    assert is_done(task, there, elsewhere) and not is_done(task, elsewhere, elsewhere)


def test_a_task_that_may_be_given_is_never_already_done() -> None:
    sim, rng = TabletopSim(), np.random.default_rng(0)
    seen = set()
    for _ in range(40):
        sim.place_randomly(rng)
        now = sim.scene()
        for family, tasks in applicable_tasks(now).items():
            seen.add(family)
            assert not any(is_done(task, now, now) for task in tasks), family
    assert seen >= {"block_to_region", "block_next_to_block", "block_in_direction", "effector_to_region"}
    assert all(0 <= x <= TABLE_SIZE for x in now.blocks.ravel())
