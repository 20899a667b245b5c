"""The scripted teleoperator: it solves every instruction family from seeded starts, no two of its
demonstrations are alike, and its instructions last as long as CALVIN's (mostly 20-100 steps)."""

from __future__ import annotations

import numpy as np
import pytest

from playseg_core.domains.tabletop.instructions import FAMILIES, NEXT_TO_GAP, applicable_tasks
from playseg_core.domains.tabletop.play import PlayConfig, PlayStats, Recorder, generate_episode, run_task
from playseg_core.domains.tabletop.render import Renderer
from playseg_core.domains.tabletop.sim import TabletopSim
from playseg_core.domains.tabletop.spec import BLOCK_EXTENTS
from playseg_core.domains.tabletop.teleop import TeleopConfig, Teleoperator

STARTS = 10
MAX_STEPS = PlayConfig().max_task_steps


def seeded_start(seed: int, family: str) -> tuple[Recorder, np.random.Generator]:
    """A random layout; for separate, two blocks put next to each other first."""
    rng = np.random.default_rng(seed)
    sim = TabletopSim()
    sim.place_randomly(rng)
    if family == "separate_blocks":
        scene = sim.scene()
        blocks = scene.blocks.copy()
        a, b = rng.choice(len(blocks), size=2, replace=False)
        bearing = rng.uniform(-np.pi, np.pi)
        distance = BLOCK_EXTENTS[a] + BLOCK_EXTENTS[b] + NEXT_TO_GAP / 2
        blocks[b] = np.clip(blocks[a] + distance * np.array([np.cos(bearing), np.sin(bearing)]), 0.04, 0.46)
        sim.place(blocks, scene.effector, scene.angles)
    return Recorder(sim, Renderer(32)), rng


@pytest.mark.parametrize("family", list(FAMILIES))
def test_the_teleoperator_solves_each_family_from_seeded_starts(family: str) -> None:
    solved = given = 0
    for seed in range(40):
        recorder, rng = seeded_start(seed, family)
        tasks = applicable_tasks(recorder.scene).get(family)
        if not tasks:
            continue  # e.g. the two blocks of a separate task ended up apart against a rim
        task = tasks[int(rng.integers(len(tasks)))]
        given += 1
        solved += run_task(recorder, Teleoperator(TeleopConfig(), rng), task, MAX_STEPS)
        if given == STARTS:
            break
    assert given == STARTS
    assert solved >= STARTS - 1, f"{family}: {solved} of {given} solved"


def test_no_two_demonstrations_of_one_instruction_are_alike() -> None:
    runs = []
    for operator_seed in (1, 2, 3):
        recorder, rng = seeded_start(5, "block_to_region")
        task = applicable_tasks(recorder.scene)["block_to_region"][0]
        solved = run_task(
            recorder, Teleoperator(TeleopConfig(), np.random.default_rng(operator_seed)), task, MAX_STEPS
        )
        assert solved
        runs.append(np.array(recorder.actions))
    lengths = {len(run) for run in runs}
    assert len(lengths) > 1 or not np.allclose(runs[0], runs[1])
    for a in range(3):
        for b in range(a + 1, 3):
            n = min(len(runs[a]), len(runs[b]))
            assert not np.allclose(runs[a][:n], runs[b][:n])


def test_instruction_lengths_spread_like_calvin() -> None:
    stats = PlayStats()
    for seed in range(4):
        stats.merge(generate_episode(PlayConfig(tasks_per_episode=(12, 12), image_size=32), seed).stats)
    lengths = np.array(stats.task_lengths)
    assert len(lengths) >= 40
    assert ((lengths >= 20) & (lengths <= 100)).mean() >= 0.75
    assert 25 <= np.median(lengths) <= 70
    assert lengths.max() <= MAX_STEPS
    assert stats.success_rate >= 0.9
