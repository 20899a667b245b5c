"""The CALVIN-shaped tabletop: its task set (at most 34 distinct task types, one wording each, closed
under the table's symmetries), play that gives only those tasks at CALVIN's lengths, and the presets'
25 % start split with enough annotated segments per task type."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.generation import Preset
from playseg_core.data.splits import SplitTargets
from playseg_core.domains.tabletop.generate import PRESETS, generate_dataset
from playseg_core.domains.tabletop.instructions import CALVIN_INSTRUCTIONS, FAMILIES, TASK_SETS, task_for
from playseg_core.domains.tabletop.play import PlayConfig, SceneRecorder, draw_task, play
from playseg_core.domains.tabletop.robot_log import replay_dataset_episode
from playseg_core.domains.tabletop.sim import TabletopSim
from playseg_core.domains.tabletop.symmetry import SYMMETRIES, turn_instruction

CALVIN = TASK_SETS["calvin"]


def test_the_calvin_set_is_at_most_34_distinct_tasks_closed_under_the_symmetries() -> None:
    texts = CALVIN.instructions
    assert 20 <= len(texts) <= 34 and len(set(texts)) == len(texts) == len(CALVIN_INSTRUCTIONS)
    assert set(texts) == set(CALVIN_INSTRUCTIONS)
    for text in texts:  # each is a task the oracle knows, worded as its family words it
        task = task_for(text)
        assert FAMILIES[task.family].wording.split(" {")[0] in text
    for number in range(len(SYMMETRIES)):
        assert {turn_instruction(text, number) for text in texts} == set(texts)
    assert turn_instruction("push the red cube left", 1) != "push the red cube left"  # the turn is real
    assert TASK_SETS["all"].instructions == tuple(t.text for f in FAMILIES.values() for t in f.tasks)


def test_draw_task_of_the_calvin_set_draws_its_tasks_about_uniformly() -> None:
    rng = np.random.default_rng(3)
    drawn: Counter[str] = Counter()
    for _ in range(120):
        sim = TabletopSim()
        sim.place_randomly(rng)
        scene = sim.scene()
        for _ in range(10):
            task = draw_task(scene, rng, tasks=CALVIN)
            assert task is not None
            drawn[task.text] += 1
    assert set(drawn) == set(CALVIN.instructions)  # every type, nothing else
    # uniform over the tasks that may be given: no type starved (by family, the 16 pushes would share
    # a quarter of the draws, 1/64 each, against 1/32 uniformly)
    assert min(drawn.values()) >= 0.4 * sum(drawn.values()) / len(drawn)


def test_calvin_play_gives_only_its_tasks_at_calvins_lengths() -> None:
    config = PlayConfig(task_set="calvin")
    lengths: list[int] = []
    for seed in range(8):
        _, segments, stats = play(config, 500 + seed, SceneRecorder)
        assert segments and all(s.instruction in CALVIN.instructions for s in segments)
        lengths += stats.task_lengths
    assert 30 <= float(np.median(lengths)) <= 60  # CALVIN's instructions: 32-64 steps at 10 Hz
    with pytest.raises(ValueError, match="unknown tabletop task set 'nope'"):
        PlayConfig(task_set="nope")


def test_the_calvin_presets_are_a_25_percent_start_split_with_30_per_task_type() -> None:
    for name in ("calvin-small", "calvin"):
        preset = PRESETS[name]
        targets = preset.targets
        assert preset.play.task_set == "calvin" and targets.test_segments > 0
        share = targets.annotated_segments / (targets.annotated_segments + targets.play_segments)
        assert share == pytest.approx(0.25)
    # the least drawn type comes about 2/3 as often as the mean: 1,800 annotated segments give it ~37
    assert PRESETS["calvin"].targets.annotated_segments >= 45 * len(CALVIN.instructions)


def test_a_calvin_dataset_lists_the_set_and_replays_from_its_seeds(tmp_path: Path) -> None:
    preset = Preset(
        "calvin-test",
        "a few short calvin episodes",
        PlayConfig(task_set="calvin", tasks_per_episode=(3, 4), image_size=32),
        SplitTargets(test_segments=3, annotated_segments=6, play_segments=3, val_fraction=0.25),
    )
    generate_dataset(tmp_path / "d", preset, seed=1, progress=False)
    data = PlayDataset.open(tmp_path / "d")
    assert data.instructions == CALVIN.instructions
    truth = [data.segments(index, truth=True) for index in range(len(data.records))]
    assert all(s.instruction in CALVIN.instructions for segments in truth for s in segments)
    meta = json.loads((tmp_path / "d" / "meta/info.json").read_text())["meta"]
    assert meta["play_config"]["task_set"] == "calvin"
    log = replay_dataset_episode(data, 0)  # the replay reads the task set from the dataset's meta
    assert log.segments == truth[0]


def test_the_policy_evaluation_gives_the_task_set_of_its_config() -> None:
    from playseg_core.domains.tabletop.evaluation import evaluation_episodes
    from playseg_core.domains.tabletop.learner import TabletopPolicyLearner
    from playseg_core.errors import PlaysegError

    calvin = {e.task.text for e in evaluation_episodes(60, 9, CALVIN)}
    every = {e.task.text for e in evaluation_episodes(60, 9)}
    assert calvin <= set(CALVIN.instructions) and len(calvin) >= 20
    assert not every <= set(CALVIN.instructions)  # the default is all 197
    assert TabletopPolicyLearner.from_config({"task_set": "calvin", "steps": 1}).task_set == "calvin"
    with pytest.raises(PlaysegError, match="task_set must be one of"):
        TabletopPolicyLearner.from_config({"task_set": "nope"})
