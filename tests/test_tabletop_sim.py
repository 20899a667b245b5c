"""The tabletop world: physics (pushing, friction, rims, the effector's reach, the action bounds),
determinism, and the top-down camera."""

from __future__ import annotations

import numpy as np
import pytest

from playseg_core.domains.tabletop.play import PlayConfig
from playseg_core.domains.tabletop.render import EFFECTOR_RGB, VIEW_BORDER, Renderer
from playseg_core.domains.tabletop.sim import TabletopSim, physics_stepper
from playseg_core.domains.tabletop.spec import (
    BLOCK_EXTENTS,
    BLOCKS,
    COLOUR_RGB,
    EFFECTOR_RADIUS,
    EFFECTOR_REACH,
    MAX_SPEED,
    TABLE_SIZE,
)

BLUE_CUBE = BLOCKS.index("blue cube")
PARKED = np.array([[0.05 + 0.055 * i, 0.45] for i in range(8)])
"""Every block in a row along the top edge, out of the way."""


def sim_with(block: int, at: tuple[float, float], effector: tuple[float, float]) -> TabletopSim:
    blocks = PARKED.copy()
    blocks[block] = at
    sim = TabletopSim()
    sim.place(blocks, effector)
    return sim


def test_commands_are_clipped_to_the_bounds_and_applied_as_float32() -> None:
    sim = sim_with(BLUE_CUBE, (0.25, 0.25), (0.25, 0.1))
    applied = sim.step((1.0, -0.05))
    assert applied == (pytest.approx(MAX_SPEED), float(np.float32(-0.05)))
    for _ in range(5):
        sim.step((1.0, 0.0))
    velocity = sim.scene().effector_velocity
    assert velocity[0] == pytest.approx(MAX_SPEED, rel=1e-3) and abs(velocity[1]) < 1e-3


def test_the_effector_stops_at_the_edge_of_its_reach() -> None:
    sim = sim_with(BLUE_CUBE, (0.25, 0.25), (0.25, 0.1))
    xs = []
    for _ in range(40):
        sim.step((MAX_SPEED, -MAX_SPEED))
        xs.append(sim.scene().effector.copy())
    xs = np.array(xs)
    # The servo brakes within a couple of millimetres, then holds the edge.
    assert xs[:, 0].max() <= TABLE_SIZE + EFFECTOR_REACH + 0.002 and xs[:, 1].min() >= -EFFECTOR_REACH - 0.002
    assert xs[-1] == pytest.approx([TABLE_SIZE + EFFECTOR_REACH, -EFFECTOR_REACH], abs=1e-4)


def test_a_pushed_block_slides_while_pushed_and_stops_after() -> None:
    contact = BLOCK_EXTENTS[BLUE_CUBE] + EFFECTOR_RADIUS
    sim = sim_with(BLUE_CUBE, (0.2, 0.25), (0.2 - contact - 0.02, 0.25))
    for _ in range(15):
        sim.step((0.1, 0.0))
    pushed = sim.scene().blocks[BLUE_CUBE]
    assert pushed[0] > 0.2 + 0.08 and abs(pushed[1] - 0.25) < 0.01
    for _ in range(5):
        sim.step((-0.1, 0.0))  # the effector backs off: nothing pushes the block any more
    settled = sim.scene().blocks[BLUE_CUBE]
    for _ in range(5):
        sim.step((0.0, 0.0))
    assert np.allclose(sim.scene().blocks[BLUE_CUBE], settled, atol=1e-4)
    others = np.delete(sim.scene().blocks, BLUE_CUBE, axis=0)
    assert np.allclose(others, np.delete(PARKED, BLUE_CUBE, axis=0))


def test_the_rims_keep_blocks_on_the_table() -> None:
    sim = sim_with(BLUE_CUBE, (0.4, 0.25), (0.3, 0.25))
    for _ in range(40):
        sim.step((MAX_SPEED, 0.0))  # drives the block into the right rim and keeps pressing
    x = sim.scene().blocks[BLUE_CUBE][0]
    assert TABLE_SIZE - BLOCK_EXTENTS[BLUE_CUBE] - 0.02 < x <= TABLE_SIZE - BLOCK_EXTENTS[BLUE_CUBE] + 0.005


def test_same_start_and_actions_give_identical_states() -> None:
    actions = np.random.default_rng(1).uniform(-MAX_SPEED, MAX_SPEED, size=(120, 2))
    runs = []
    for _ in range(2):
        sim = TabletopSim()
        sim.place_randomly(np.random.default_rng(7))
        for action in actions:
            sim.step(action)
        runs.append(sim.scene())
    assert np.array_equal(runs[0].blocks, runs[1].blocks) and np.array_equal(runs[0].angles, runs[1].angles)
    start = TabletopSim()
    start.place_randomly(np.random.default_rng(7))
    assert not np.array_equal(start.scene().blocks, runs[0].blocks)  # the actions did move blocks


def test_the_fast_physics_step_is_pymunks_step() -> None:
    actions = np.random.default_rng(2).uniform(-MAX_SPEED, MAX_SPEED, size=(80, 2))
    sims = [TabletopSim(), TabletopSim()]
    sims[1]._physics_step = sims[1].space.step  # pymunk's own, with its bookkeeping
    assert physics_stepper(sims[0].space) is not sims[0].space.step  # the fast path is in use
    for sim in sims:
        sim.place_randomly(np.random.default_rng(3))
        for action in actions:
            sim.step(action)
    assert np.array_equal(sims[0].scene().blocks, sims[1].scene().blocks)
    assert np.array_equal(sims[0].scene().effector, sims[1].scene().effector)


def test_bad_input_is_a_one_line_value_error() -> None:
    sim = TabletopSim()
    with pytest.raises(ValueError, match="tabletop blocks must be 8"):
        sim.place(np.zeros((3, 2)), (0.1, 0.1))
    with pytest.raises(ValueError, match="tabletop effector"):
        sim.place(PARKED, (2.0, 0.1))
    with pytest.raises(ValueError, match="must be finite"):
        sim.step((float("nan"), 0.0))
    with pytest.raises(ValueError, match="image size must be an integer >= 16"):
        Renderer(8)
    with pytest.raises(ValueError, match="image size"):
        PlayConfig(image_size=4)


def pixel_of(renderer: Renderer, x: float, y: float) -> tuple[int, int]:
    scale = renderer.pixels_per_metre
    return int((TABLE_SIZE + VIEW_BORDER - y) * scale), int((x + VIEW_BORDER) * scale)


@pytest.mark.parametrize("size", [96, 64])
def test_the_camera_shows_blocks_and_effector_where_they_are(size: int) -> None:
    sim = sim_with(BLUE_CUBE, (0.3, 0.15), (0.1, 0.3))
    renderer = Renderer(size)
    frame = renderer.render(sim.scene())
    assert frame.shape == (size, size, 3) and frame.dtype == np.uint8
    assert tuple(frame[pixel_of(renderer, 0.3, 0.15)]) == COLOUR_RGB["blue"]
    assert tuple(frame[pixel_of(renderer, 0.1, 0.3)]) == EFFECTOR_RGB
    assert np.array_equal(frame, renderer.render(sim.scene()))
    # Half a pixel's move still changes the frame (anti-aliased, sub-pixel drawing).
    moved = sim_with(BLUE_CUBE, (0.3 + 0.5 / renderer.pixels_per_metre, 0.15), (0.1, 0.3))
    assert not np.array_equal(frame, renderer.render(moved.scene()))
