"""Tabletop play episodes: their shape, unlabelled stretches, determinism, and ground truth that the
oracle confirms when the recorded actions are replayed through the physics."""

from __future__ import annotations

import numpy as np
import pytest

from playseg_core.domains.tabletop.instructions import INSTRUCTIONS, is_done, task_for
from playseg_core.domains.tabletop.play import (
    PlayConfig,
    draw_task,
    generate_episode,
    replay_scenes,
    seed_of_episode,
)
from playseg_core.domains.tabletop.sim import TabletopSim
from playseg_core.domains.tabletop.spec import CAMERA

IDLE = PlayConfig(tasks_per_episode=(6, 6), idle_chance=1.0, idle_steps=(5, 8), image_size=48)


@pytest.fixture(scope="module")
def played():
    return generate_episode(IDLE, 11)


def test_an_episode_is_many_labelled_tasks_in_a_row(played) -> None:
    episode = played.episode
    assert len(episode.segments) == 6
    assert episode.images[CAMERA].shape == (episode.num_steps + 1, 48, 48, 3)
    assert episode.state.shape == (episode.num_steps + 1, 4) and episode.actions.shape == (
        episode.num_steps,
        2,
    )
    assert np.abs(episode.actions).max() <= 0.2 + 1e-6
    texts = [seg.instruction for seg in episode.segments]
    assert all(text in INSTRUCTIONS for text in texts)
    assert all(a != b for a, b in zip(texts, texts[1:], strict=False))  # never the same task twice in a row
    assert episode.num_steps >= 150


def test_idle_stretches_are_unlabelled_gaps(played) -> None:
    episode, stats = played.episode, played.stats
    covered = np.zeros(episode.num_steps, bool)
    previous_end = 0
    for seg in episode.segments:
        assert seg.start >= previous_end + 5  # idle_chance 1: 5-8 unlabelled steps before every task
        covered[seg.start : seg.end] = True
        previous_end = seg.end
    assert (~covered).sum() == stats.idle_steps + stats.failed_steps
    assert stats.idle_steps >= 6 * 5


def test_the_ground_truth_holds_when_the_actions_are_replayed(played) -> None:
    """Same layout, the recorded actions: the oracle says done exactly at each segment's end step."""
    episode = played.episode
    sim = TabletopSim()
    sim.place_randomly(np.random.default_rng(11))
    scenes = [sim.scene()]
    for action in episode.actions:
        sim.step(action)
        scenes.append(sim.scene())
    states = np.array([[*s.effector, *s.effector_velocity] for s in scenes], np.float32)
    np.testing.assert_array_equal(states, episode.state)  # the replay is the recording
    for seg in episode.segments:
        task, start = task_for(seg.instruction), scenes[seg.start]
        done = [is_done(task, scenes[t], start) for t in range(seg.start + 1, seg.end + 1)]
        assert done[-1] and not any(done[:-1]), seg


def test_replay_scenes_gives_the_recorded_episode_s_scenes_and_checks_its_commands(played) -> None:
    episode = played.episode
    assert seed_of_episode(episode.episode_id) == 11
    scenes, segments = replay_scenes(IDLE, episode.episode_id, episode.actions)
    states = np.array([[*s.effector, *s.effector_velocity] for s in scenes], np.float32)
    np.testing.assert_array_equal(states, episode.state)
    assert segments == episode.segments
    # Other commands than the replay's (another play config): one line naming the episode.
    with pytest.raises(ValueError, match="episode tabletop-11: replaying its seed gives other commands"):
        replay_scenes(IDLE, episode.episode_id, episode.actions + 0.01)
    with pytest.raises(ValueError, match="episode 'babyai-3': not a generated tabletop episode"):
        seed_of_episode("babyai-3")


def test_same_seed_same_episode_other_seed_another() -> None:
    config = PlayConfig(tasks_per_episode=(3, 3), image_size=32)
    a, b, c = (generate_episode(config, seed).episode for seed in (4, 4, 5))
    assert a.segments == b.segments and np.array_equal(a.actions, b.actions)
    assert np.array_equal(a.images[CAMERA], b.images[CAMERA]) and np.array_equal(a.state, b.state)
    assert a.segments != c.segments


def test_draw_task_gives_only_tasks_not_done_and_not_the_previous_one() -> None:
    sim, rng = TabletopSim(), np.random.default_rng(3)
    sim.place_randomly(rng)
    scene = sim.scene()
    previous = None
    for _ in range(50):
        task = draw_task(scene, rng, exclude=previous)
        assert task is not None and task != previous and not is_done(task, scene, scene)
        previous = task


def test_bad_play_settings_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match="tasks_per_episode"):
        PlayConfig(tasks_per_episode=(5, 2))
    with pytest.raises(ValueError, match="idle_chance"):
        PlayConfig(idle_chance=1.5)


def test_failed_tasks_leave_their_steps_unlabelled_and_end_the_episode() -> None:
    # Three steps are too few for any task: every attempt fails.
    played = generate_episode(PlayConfig(max_task_steps=3, max_failures=2, idle_chance=0.0, image_size=32), 0)
    assert played.episode.segments == []
    assert played.episode.num_steps == 2 * 3 == played.stats.failed_steps
    assert sum(played.stats.attempted.values()) == 2 and sum(played.stats.solved.values()) == 0
