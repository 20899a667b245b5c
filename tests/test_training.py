"""Training samples (the paper's negatives), batches, and short training runs that must learn."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from test_models import INSTRUCTIONS, synthetic_episode, tiny_model_config

from playseg_core.data.episode import Episode, Segment
from playseg_core.domains.babyai.spec import CAMERA
from playseg_core.ps.encoders import StepEncoders
from playseg_core.ps.model import PSModel
from playseg_core.ps.samples import NEGATIVE_KINDS, label_index, make_batch, segment_samples
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.symmetries import camera_symmetries
from playseg_core.ps.training import (
    TrainConfig,
    step_cap,
    train_labeller,
    train_ps,
    training_symmetries,
)


def encoders_for(size: int = 64) -> StepEncoders:
    cfg = tiny_model_config(size=size)
    return StepEncoders(cfg.encoders, cfg.features)


torch.set_num_threads(1)


def test_middle_segment_gets_all_five_negatives_inside_the_episode() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        samples = segment_samples(20, 26, num_steps=50, max_len=25, k_max=5, rng=rng)
        kinds = [s.kind for s in samples]
        assert kinds == ["positive", *NEGATIVE_KINDS]
        for s in samples:
            assert 0 <= s.start < s.end <= 50 and s.end - s.start <= 25
            assert s.is_end == (s.kind == "positive")
        by_kind = {s.kind: s for s in samples}
        # The end head is a hazard: nothing from the true start is supervised past the true end.
        assert not any(s.start == 20 and s.end > 26 for s in samples)
        assert by_kind["end_earlier"].start == 20 and 21 <= by_kind["end_earlier"].end <= 25
        widened = by_kind["widened"]
        assert 15 <= widened.start <= 19 and 27 <= widened.end <= 31
        assert by_kind["before"].end == 20 and 15 <= by_kind["before"].start <= 19
        left, right = by_kind["shift_left"], by_kind["shift_right"]
        assert left.end - left.start == 6 and 15 <= left.start <= 19
        assert right.end - right.start == 6 and 21 <= right.start <= 25


def test_shifts_cover_exactly_one_to_k_max() -> None:
    rng = np.random.default_rng(1)
    seen = set()
    for _ in range(300):
        samples = segment_samples(20, 26, num_steps=50, max_len=25, k_max=3, rng=rng)
        seen.add(next(s for s in samples if s.kind == "shift_right").start - 20)
    assert seen == {1, 2, 3}


def test_corner_cases_stay_inside_the_episode() -> None:
    rng = np.random.default_rng(2)
    # At the episode start: nothing can move left.
    kinds = {s.kind for s in segment_samples(0, 4, 30, 25, 5, rng)}
    assert kinds == {"positive", "end_earlier", "shift_right"}
    # At the episode end: nothing can move right.
    kinds = {s.kind for s in segment_samples(26, 30, 30, 25, 5, rng)}
    assert kinds == {"positive", "end_earlier", "before", "shift_left"}
    # A one-step segment cannot end earlier; the only room left is one step, so k = 1.
    samples = segment_samples(1, 2, 3, 25, 5, rng)
    assert "end_earlier" not in {s.kind for s in samples}
    assert all(0 <= s.start < s.end <= 3 for s in samples)
    # L_max bounds the widened window; a segment of exactly L_max cannot grow.
    kinds = {s.kind for s in segment_samples(10, 20, 40, 10, 5, rng)}
    assert "widened" not in kinds and "shift_left" in kinds
    # A segment longer than L_max yields nothing.
    assert segment_samples(0, 12, 40, 10, 5, rng) == []


def test_no_negative_starts_at_an_annotated_start_and_ends_at_or_past_its_end() -> None:
    # A 2-step annotated segment [4, 6) before [6, 12): with k_max 5 the window-before, shifted and
    # widened negatives of [6, 12) can start at 4 and end at or past 6, which would tell the end head
    # "not ended" where [4, 6) ends, or past it.
    base = synthetic_episode(3, num_segments=8)
    assert base.num_steps >= 16
    bounds = [0, 4, 6, 12, base.num_steps]
    segments = [
        Segment(a, b, INSTRUCTIONS[i % len(INSTRUCTIONS)])
        for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True))
    ]
    episode = Episode(base.episode_id, base.actions, base.images, segments=segments)
    rng = np.random.default_rng(0)
    negatives_from_other_starts = 0
    for _ in range(50):
        batch = make_batch([(episode, segments[2])], label_index(INSTRUCTIONS), encoders_for(), 10, 5, rng)
        for row in range(len(batch.end_target)):
            start = 1 + int(batch.window_index[row, 0])  # the batch's rows start k_max before step 6
            for position in torch.nonzero(batch.end_weight[row] > 0).flatten().tolist():
                if batch.end_target[row, position] == 0 and start != 6:
                    negatives_from_other_starts += 1
                    assert not (start == 4 and start + position >= 6)
    assert negatives_from_other_starts > 50


def test_batch_windows_never_cross_episodes() -> None:
    episodes = [synthetic_episode(s, num_segments=3) for s in range(3)]
    rng = np.random.default_rng(0)
    items = [(ep, seg) for ep in episodes for seg in ep.segments]
    batch = make_batch(
        items, label_index(INSTRUCTIONS), encoders_for(), 6, 3, rng, dense_prefix_negatives=True
    )
    # Each segment contributes the frames [start - k_max, end + k_max] of its episode, clipped.
    regions = [(max(0, s.start - 3), min(ep.num_steps, s.end + 3)) for ep, s in items]
    total = sum(hi - lo + 1 for lo, hi in regions)
    assert len(batch.inputs[CAMERA]) == total
    starts = np.cumsum([0] + [hi - lo + 1 for lo, hi in regions])
    for row in batch.window_index.numpy():
        region = np.searchsorted(starts, row[0], side="right") - 1
        inside = row[row < total]
        assert inside.max() <= starts[region + 1] - 1  # past the region: the zero row
        assert np.all(np.diff(inside) == 1)
    # Every positive is supervised as an end; dense prefixes add "not ended" before it, nothing after.
    assert len(batch.labels) == sum(len(ep.segments) for ep in episodes)
    ends = batch.end_target[batch.label_window, batch.label_position]
    assert torch.all(ends == 1)
    positives = batch.end_weight[batch.label_window]
    for row, length in zip(positives, batch.label_position.tolist(), strict=True):
        assert torch.all(row[1 : length + 1] == 1) and row[0] == 0
        assert torch.all(row[length + 1 :] == 0)


def _small_data(ends_in_actions: bool = False, starts_in_actions: bool = False) -> tuple[list, list]:
    def episode(seed: int) -> Episode:
        return synthetic_episode(
            seed,
            num_segments=5,
            size=16,
            ends_in_actions=ends_in_actions,
            starts_in_actions=starts_in_actions,
        )

    return [episode(s) for s in range(16)], [episode(100 + s) for s in range(4)]


def _train_small_ps(
    dense: bool,
    epochs: int,
    num_actions: int = 0,
    ends_in_actions: bool = False,
    starts_in_actions: bool = False,
    end_lookahead: int = 0,
):
    train, val = _small_data(ends_in_actions, starts_in_actions)
    cfg = TrainConfig(
        epochs=epochs,
        segments_per_batch=5,
        lr=5e-3,
        dense_prefix_negatives=dense,
        augment=False,
        progress=False,
        log_epochs=False,
        num_threads=1,
    )
    model_cfg = tiny_model_config(
        max_len=8, num_actions=num_actions, num_layers=1, size=16, end_lookahead=end_lookahead
    )
    return train_ps(train, val, INSTRUCTIONS, cfg, model_cfg), val


def _boundary_hits(model, episodes) -> tuple[float, float, float]:
    """Exact-boundary precision and recall of `model` on `episodes`, and label accuracy of the hits."""
    hits = predicted = true = correct_labels = 0
    for episode in episodes:
        pred = segment_episode(model, episode)
        truth = {(s.start, s.end): s.instruction for s in episode.segments}
        matched = [s for s in pred if (s.start, s.end) in truth]
        hits += len(matched)
        correct_labels += sum(s.instruction == truth[(s.start, s.end)] for s in matched)
        predicted += len(pred)
        true += len(truth)
    return hits / predicted, hits / true, correct_labels / max(1, hits)


@pytest.mark.slow
def test_short_ps_training_learns_to_segment() -> None:
    result, val = _train_small_ps(dense=True, epochs=30)
    first = result.history[0]
    best = min(result.history, key=lambda h: h["val_loss"])
    assert best["val_loss"] < 0.3 * first["val_loss"]
    assert best["val_label_accuracy"] >= 0.9  # chance: 0.25
    # The trained model segments held-out episodes: exact boundaries and labels.
    precision, recall, labels = _boundary_hits(result.model, val)
    assert precision >= 0.8 and recall >= 0.8  # an untrained model: ~0.2
    assert labels >= 0.9


@pytest.mark.slow
def test_a_model_that_reads_actions_learns_ends_only_the_actions_show() -> None:
    # Frames carry no end marker here; the last action of each segment is the only sign of its end.
    with_actions, val = _train_small_ps(dense=True, epochs=30, num_actions=3, ends_in_actions=True)
    frames_only, _ = _train_small_ps(dense=True, epochs=30, ends_in_actions=True)
    precision, recall, _ = _boundary_hits(with_actions.model, val)
    blind_precision, blind_recall, _ = _boundary_hits(frames_only.model, val)
    assert precision >= 0.8 and recall >= 0.8
    assert blind_precision + blind_recall < precision + recall - 0.3


@pytest.mark.slow
def test_an_end_head_with_lookahead_learns_ends_only_the_next_action_shows() -> None:
    # Each segment's first action is the only sign of a boundary: a segment's end shows one step later.
    ahead, val = _train_small_ps(
        dense=True, epochs=30, num_actions=3, starts_in_actions=True, end_lookahead=1
    )
    causal, _ = _train_small_ps(dense=True, epochs=30, num_actions=3, starts_in_actions=True)
    precision, recall, _ = _boundary_hits(ahead.model, val)
    causal_precision, causal_recall, _ = _boundary_hits(causal.model, val)
    assert precision >= 0.8 and recall >= 0.8
    assert causal_precision + causal_recall < precision + recall - 0.3


@pytest.mark.slow
def test_short_ps_training_without_dense_prefixes_still_learns() -> None:
    result, _ = _train_small_ps(dense=False, epochs=20)
    first = result.history[0]
    best = min(result.history, key=lambda h: h["val_loss"])
    assert best["val_loss"] < 0.5 * first["val_loss"]
    assert best["val_label_accuracy"] >= 0.8


@pytest.mark.slow
def test_short_labeller_training_learns() -> None:
    train, val = _small_data()
    cfg = TrainConfig(
        epochs=20,
        segments_per_batch=5,
        lr=5e-3,
        augment=False,
        progress=False,
        log_epochs=False,
        num_threads=1,
    )
    model_cfg = tiny_model_config(max_len=8, num_layers=1, size=16)
    result = train_labeller(train, val, INSTRUCTIONS, cfg, model_cfg)
    assert max(h["val_label_accuracy"] for h in result.history) >= 0.8  # chance: 0.25
    assert result.history[-1]["train_loss"] < 0.3 * result.history[0]["train_loss"]


def test_augmentation_rotates_or_mirrors_each_clip_as_a_whole() -> None:
    episode = synthetic_episode(3, num_segments=2, size=16)
    items = [(episode, episode.segments[1])]  # one clip: the frames within k_max of this segment
    encoders = encoders_for(size=16)
    plain = make_batch(items, label_index(INSTRUCTIONS), encoders, 8, 2, np.random.default_rng(0))
    seen = set()
    for seed in range(12):
        augmented = make_batch(
            items, label_index(INSTRUCTIONS), encoders, 8, 2, np.random.default_rng(seed),
            symmetries=camera_symmetries(encoders.cameras),
        )  # fmt: skip
        original, changed = plain.inputs[CAMERA].numpy(), augmented.inputs[CAMERA].numpy()
        for k in range(4):
            for mirror in (False, True):
                candidate = np.rot90(original, k=k, axes=(1, 2))
                candidate = candidate[:, :, ::-1] if mirror else candidate
                if np.array_equal(candidate, changed):
                    seen.add((k, mirror))
    assert len(seen) >= 3  # different seeds give different transforms, each a whole-clip dihedral one


def test_augment_without_a_domains_symmetries_turns_frames_only_for_models_that_read_no_actions() -> None:
    """The camera frames' rotations leave the actions as they are (a mirror would swap left and right
    turns): a model that reads actions gets a clear error instead of wrongly turned clips."""
    frames_only, with_actions = (
        StepEncoders(cfg.encoders, cfg.features)
        for cfg in (tiny_model_config(size=16), tiny_model_config(size=16, num_actions=3))
    )
    assert training_symmetries(TrainConfig(augment=False), with_actions) is None
    symmetries = training_symmetries(TrainConfig(augment=True), frames_only)
    assert symmetries is not None and symmetries.count == 8
    with pytest.raises(ValueError, match="read no actions"):
        training_symmetries(TrainConfig(augment=True), with_actions)


@pytest.mark.parametrize("lookahead", [0, 2])
def test_training_windows_read_the_rows_segmenting_reads(lookahead: int) -> None:
    """At every supervised position the end logit of a training window equals the offline end-logit
    matrix's: the same rows past the end (not zero rows where the episode goes on)."""
    torch.manual_seed(0)
    model = PSModel(tiny_model_config(max_len=6, size=16, end_lookahead=lookahead), INSTRUCTIONS).eval()
    episode = synthetic_episode(5, num_segments=5, max_seg_len=4, size=16)
    checked = 0
    with torch.no_grad():
        offline = model.end_logits(model.encode_episode(episode)) - model.end_bias
        for index, segment in enumerate(episode.segments):
            batch = make_batch(
                [(episode, segment)], label_index(INSTRUCTIONS), model.encoders, 6, 2,
                np.random.default_rng(index), dense_prefix_negatives=True, lookahead=lookahead,
            )  # fmt: skip
            features = model.encode_steps(batch.inputs)
            rows = torch.cat([features, features.new_zeros(1, features.shape[1])])[batch.window_index]
            logits = model.raw_end_logits(model.trunk(rows, batch.starts_episode))
            first_step = max(0, segment.start - 2)  # a batch's rows start k_max before its segment
            for row, supervised in enumerate(batch.end_weight > 0):
                start = first_step + int(batch.window_index[row, 0])
                for position in torch.nonzero(supervised).flatten().tolist():
                    torch.testing.assert_close(logits[row, position], offline[start, position - 1])
                    checked += 1
    assert checked > 20


def test_the_step_cap_scales_with_the_data() -> None:
    cfg = TrainConfig()
    assert step_cap(cfg, 500) == 16 * 500  # paper scale: 16 epochs
    assert step_cap(cfg, 100) == 3200  # small data: at least min_steps
    assert step_cap(replace(cfg, cap_steps=1000), 500) == 1000
    assert step_cap(replace(cfg, epochs=3), 7) == 21  # exactly the epochs asked for
    assert step_cap(replace(cfg, epochs=3, max_steps=5), 7) == 5  # --max-steps bounds everything


def test_a_recorded_clip_gives_the_episode_s_rows() -> None:
    """`recorded_clip` then `clip_inputs` (what make_batch does, a domain's symmetry between them) give the
    rows `episode_inputs` gives for o_first..o_last: from o_0 (its previous action "none") and from later
    steps (o_first's previous action a_{first-1}), for a discrete action here."""
    cfg = tiny_model_config(num_actions=3)
    encoders = StepEncoders(cfg.encoders, cfg.features)
    episode = synthetic_episode(4, ends_in_actions=True)
    whole = encoders.episode_inputs(episode)
    for first, last in ((0, 5), (3, 9), (1, episode.num_steps)):
        recorded = encoders.recorded_clip(episode, first, last)
        rows = encoders.clip_inputs(recorded, first, "episode")
        assert set(rows) == set(whole)
        for feature, expected in whole.items():
            np.testing.assert_array_equal(rows[feature], expected[first : last + 1])
