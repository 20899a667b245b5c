"""Policy augmentation: versioned retraining on annotated + buffered segments, buffer export."""

from pathlib import Path

import numpy as np
import pytest

from playseg_core.augment.retraining import (
    AugmentationTrainer,
    TrainerConfig,
    annotated_clips,
    export_buffer_dataset,
)
from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import SegmentClip
from playseg_core.data.features import DEFAULT_CAMERA
from playseg_core.domains.babyai.imitation import PolicyTrainConfig
from playseg_core.domains.babyai.learner import FilmPolicyLearner, demonstration
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.policy import PolicyConfig
from playseg_core.domains.babyai.spec import CAMERA


@pytest.fixture(scope="module")
def episodes():
    return [generate_episode(PlayConfig(), seed) for seed in (5, 6)]


def _config(tmp_path) -> TrainerConfig:
    return TrainerConfig(str(tmp_path / "buf"), str(tmp_path / "ckpt"), eval_episodes=4)


def _learner() -> FilmPolicyLearner:
    train = PolicyTrainConfig(steps=15, batch_size=32, log_every=5, policy=PolicyConfig(channels=16))
    return FilmPolicyLearner(train)


def test_demonstrations_are_the_segments_states_and_actions(episodes):
    clips = annotated_clips(episodes)
    assert len(clips) == sum(len(e.segments) for e in episodes)
    instruction, states, actions = demonstration(clips[1])
    seg = episodes[0].segments[1]
    assert instruction == seg.instruction
    np.testing.assert_array_equal(states, episodes[0].state[seg.start : seg.end + 1])
    np.testing.assert_array_equal(actions, episodes[0].actions[seg.start : seg.end])


@pytest.mark.slow
def test_retraining_writes_versions_that_survive_a_restart(tmp_path, episodes):
    trainer = AugmentationTrainer(_config(tmp_path), _learner(), annotated_clips(episodes[:1]))
    assert trainer.policy_version == 0
    for seg in episodes[1].segments:
        trainer.add(SegmentClip.from_episode(episodes[1], seg, "test-model"))
    first = trainer.retrain()
    second = trainer.retrain()
    assert (first.version, second.version) == (1, 2)
    assert first.num_base_segments == len(episodes[0].segments)
    assert first.num_buffer_segments == len(episodes[1].segments)
    assert 0.0 <= second.success_rate <= 1.0 and second.eval_episodes == 4
    trainer.close()
    reopened = AugmentationTrainer(_config(tmp_path), _learner())
    assert reopened.policy_version == 2 and len(reopened.buffer) == len(episodes[1].segments)
    # the same policy scores the same on the fixed evaluation episodes, episode by episode
    again = reopened.evaluate()
    assert again.success_rate == second.success_rate
    _, meta = _learner().load(Path(second.checkpoint))
    assert meta["episode_success"] == "".join("01"[ok] for ok in again.episode_success)
    reopened.close()


def test_low_confidence_segments_are_stored_but_not_trained_on(tmp_path, episodes):
    config = _config(tmp_path)
    config.min_confidence = 0.5
    trainer = AugmentationTrainer(config, _learner())
    for i, seg in enumerate(episodes[0].segments):
        clip = SegmentClip.from_episode(episodes[0], seg, "m")
        clip.segment = type(seg)(seg.start, seg.end, seg.instruction, confidence=0.9 if i % 2 else 0.1)
        trainer.add(clip)
    assert len(trainer.buffer) == len(episodes[0].segments)
    assert len(trainer.training_clips()) == len(episodes[0].segments) // 2
    trainer.close()


def test_buffer_exports_as_a_dataset(tmp_path, episodes):
    trainer = AugmentationTrainer(_config(tmp_path), _learner())
    clips = [SegmentClip.from_episode(episodes[0], seg, "m") for seg in episodes[0].segments[:3]]
    for clip in clips:
        trainer.add(clip)
    assert export_buffer_dataset(trainer.buffer, tmp_path / "exported") == 3
    dataset = PlayDataset.open(tmp_path / "exported")
    exported = list(dataset.episodes("train"))
    assert [e.episode_id for e in exported] == [
        f"{c.episode_id}:{c.segment.start}-{c.segment.end}" for c in clips
    ]
    for episode, clip in zip(exported, clips, strict=True):
        np.testing.assert_array_equal(episode.images[CAMERA], clip.images[CAMERA])
        np.testing.assert_array_equal(episode.actions, clip.actions)
        assert [s.instruction for s in episode.segments] == [clip.segment.instruction]
        assert episode.segments[0].length == clip.segment.length
    with pytest.raises(FileExistsError):
        export_buffer_dataset(trainer.buffer, tmp_path / "exported")
    trainer.close()


def test_a_clip_without_what_the_policy_reads_is_refused_before_it_is_stored(tmp_path, episodes):
    trainer = AugmentationTrainer(_config(tmp_path), _learner())
    seg = episodes[0].segments[0]
    clip = SegmentClip.from_episode(episodes[0], seg, "test-model")
    stateless = SegmentClip(clip.episode_id, seg, clip.actions, clip.images, None, "test-model")
    with pytest.raises(
        ValueError, match=r"segment babyai-5\[0, \d+\): policy babyai.film reads observation.state"
    ):
        trainer.add(stateless)
    assert len(trainer.buffer) == 0  # nothing stored: later retrainings are not poisoned
    trainer.add(clip)
    assert len(trainer.buffer) == 1
    trainer.close()


def test_export_follows_the_declared_features(tmp_path, episodes):
    """Clips from LabelledSegment messages carry a float32 state and, without a declaration, an unnamed
    camera; exported with the base data's features they read back as that data declares them."""
    features = PlayConfig().features
    trainer = AugmentationTrainer(_config(tmp_path), _learner())
    seg = episodes[0].segments[0]
    clip = SegmentClip.from_episode(episodes[0], seg, "ps")
    as_received = SegmentClip(
        clip.episode_id,
        seg,
        clip.actions,
        {DEFAULT_CAMERA: clip.images[CAMERA]},
        clip.state.astype(np.float32),
    )
    trainer.add(as_received)
    assert export_buffer_dataset(trainer.buffer, tmp_path / "ds", ["x"], features, "babyai") == 1
    dataset = PlayDataset.open(tmp_path / "ds")
    assert dataset.features == features and dataset.domain == "babyai"
    exported = dataset.episode(0)
    assert exported.state.dtype == np.uint8 and list(exported.images) == [CAMERA]
    np.testing.assert_array_equal(exported.state, clip.state)
    trainer.close()


def test_a_segment_received_again_is_stored_once(tmp_path, episodes):
    """A replayed episode or a second segmenter sends the same segments again: one copy is kept."""
    trainer = AugmentationTrainer(_config(tmp_path), _learner())
    seg = episodes[0].segments[0]
    clip = SegmentClip.from_episode(episodes[0], seg, "ps")
    trainer.add(clip)
    trainer.add(clip)
    other_model = SegmentClip.from_episode(episodes[0], seg, "ps-2")  # another model's: kept
    trainer.add(other_model)
    assert len(trainer.buffer) == 2 and trainer.duplicates == 1
    trainer.close()
    reopened = AugmentationTrainer(_config(tmp_path), _learner())  # the rule survives a restart
    reopened.add(clip)
    assert len(reopened.buffer) == 2 and reopened.duplicates == 1
    reopened.close()


def test_a_success_change_is_called_a_gain_only_beyond_two_standard_errors() -> None:
    from playseg_core.augment.policy import describe_success_change, success_difference_noise

    rng = np.random.default_rng(0)
    before = rng.random(512) < 0.5
    assert success_difference_noise(before, before) == 0.0  # the same outcomes: no evaluation noise
    assert success_difference_noise(before, before, seed_std=0.02) == pytest.approx(0.02 * 2**0.5)
    independent = rng.random(512) < 0.5
    assert success_difference_noise(before, independent) == pytest.approx((2 * 0.25 / 512) ** 0.5, rel=0.1)
    # 40 more episodes solved, 8 lost: a clear gain on the same episodes
    after = before.copy()
    after[np.flatnonzero(~before)[:40]] = True
    after[np.flatnonzero(before)[:8]] = False
    assert "a gain beyond" in describe_success_change(before, after)
    assert "a drop beyond" in describe_success_change(after, before)
    assert "no measurable change" in describe_success_change(before, after, seed_std=0.05)  # seeds: noisy
    few = slice(0, 20)
    assert "no measurable change" in describe_success_change(before[few], after[few])  # few episodes
    with pytest.raises(ValueError, match="same episodes"):
        success_difference_noise(before, after[:10])
