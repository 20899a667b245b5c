"""End-to-end segmentation: fast path == reference-style path == online decoding; label calibration."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_models import INSTRUCTIONS, synthetic_episode, tiny_ps_model

from playseg_core.data.episode import Episode, Segment
from playseg_core.domains.babyai.spec import CAMERA
from playseg_core.ps.calibration import (
    calibrate_end_bias,
    calibrate_on_annotated,
    calibrate_on_own_cuts,
    calibrate_ps_model,
    calibrate_threshold,
    check_own_cuts,
    majority_instructions,
    pick_end_bias,
    steps_labelled_right,
)
from playseg_core.ps.decoding import OnlineDecoder
from playseg_core.ps.labelling import KeepRule, label_segments, segment_probability
from playseg_core.ps.metrics import BoundaryCounts, match_boundaries
from playseg_core.ps.reference_style import reference_style_segment
from playseg_core.ps.segmentation import segment_episode

torch.set_num_threads(1)


@pytest.mark.slow
@pytest.mark.parametrize(("seed", "num_actions", "end_bias"), [(0, 0, 0.0), (1, 0, 0.0), (2, 3, -0.7)])
def test_reference_style_equals_fast_segmentation(seed: int, num_actions: int, end_bias: float) -> None:
    model = tiny_ps_model(max_len=5, seed=seed, num_actions=num_actions)
    model.end_bias.fill_(end_bias)
    episode = synthetic_episode(seed, num_segments=4, max_seg_len=4)
    fast = segment_episode(model, episode)
    slow = reference_style_segment(model, episode)
    assert [(s.start, s.end, s.instruction) for s in fast] == [(s.start, s.end, s.instruction) for s in slow]
    for a, b in zip(fast, slow, strict=True):
        assert a.confidence == pytest.approx(b.confidence, abs=1e-4)
        assert a.log_prob == pytest.approx(b.log_prob, abs=1e-4)


def test_segmentation_covers_the_episode_with_known_labels() -> None:
    model = tiny_ps_model(max_len=4, seed=3)
    episode = synthetic_episode(7, num_segments=5)
    segments = segment_episode(model, episode)
    assert segments[0].start == 0 and segments[-1].end == episode.num_steps
    for previous, current in zip(segments, segments[1:], strict=False):
        assert previous.end == current.start
    assert all(1 <= s.length <= 4 and s.instruction in INSTRUCTIONS for s in segments)
    assert all(0 < s.confidence <= 1 and s.log_prob <= 0 for s in segments)


def test_online_decoding_with_end_columns_matches_offline() -> None:
    model = tiny_ps_model(max_len=5, seed=2)
    episode = synthetic_episode(5, num_segments=5)
    offline = [(s.start, s.end) for s in segment_episode(model, episode)]
    features = model.encode_episode(episode)
    decoder = OnlineDecoder(max_len=model.max_len)
    online = []
    with torch.no_grad():
        for t in range(1, episode.num_steps + 1):
            first = max(0, t - model.max_len)
            column = model.end_column(features[first : t + 1], starts_episode=first == 0)
            online += decoder.push(column.double().numpy())
    online += decoder.finish()
    assert online == offline


def test_label_segments_uses_the_label_head() -> None:
    model = tiny_ps_model(max_len=5)
    episode = synthetic_episode(2, num_segments=3)
    spans = [(seg.start, seg.end) for seg in episode.segments]
    labelled = label_segments(model, episode, spans)
    features = model.encode_episode(episode)
    for seg in labelled:
        with torch.no_grad():
            probs = torch.softmax(model.label_logits(features, seg.start, seg.end).double(), -1)
        assert seg.instruction == INSTRUCTIONS[int(probs.argmax())]
        assert seg.confidence == pytest.approx(float(probs.max()))


def test_calibrate_threshold_reaches_the_target_with_most_items() -> None:
    confidences = [0.99, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5]
    correct = [True, True, True, False, True, False, False]
    # Top 3: 1.0; top 5: 0.8; top 4: 0.75 -> for 0.8 the lowest threshold is 0.7 (five kept).
    assert calibrate_threshold(confidences, correct, 0.8) == 0.7
    assert calibrate_threshold(confidences, correct, 0.95) == 0.9
    assert calibrate_threshold(confidences, correct, 0.5) == 0.5
    assert calibrate_threshold([0.9, 0.8], [False, True], 0.9) == math.inf
    # Equal confidences are kept or dropped together.
    assert calibrate_threshold([0.9, 0.9, 0.5], [True, False, True], 0.9) == math.inf
    with pytest.raises(ValueError, match="target_accuracy"):
        calibrate_threshold([0.5], [True], 0.0)


def test_calibrated_threshold_keeps_accurate_items_on_random_data() -> None:
    rng = np.random.default_rng(0)
    confidences = rng.uniform(size=2000)
    correct = rng.uniform(size=2000) < confidences  # calibrated: P(correct) = confidence
    threshold = calibrate_threshold(confidences, correct, 0.9)
    kept = confidences >= threshold
    assert correct[kept].mean() >= 0.9
    assert 0.6 < threshold < 0.95  # most of the mass above 0.8 is needed for 90% accuracy


def test_calibrate_on_annotated_and_keep_by_label() -> None:
    model = tiny_ps_model(max_len=5)
    episodes = [synthetic_episode(s, num_segments=3) for s in range(3)]
    calibration = calibrate_on_annotated(model, episodes, target_accuracy=0.5)
    assert calibration.num_segments == 9
    if math.isfinite(calibration.threshold):
        assert calibration.accuracy_kept >= 0.5
    segments = segment_episode(model, episodes[0])
    kept = [s for s in segments if KeepRule("label", calibration.threshold).keeps(s)]
    assert all(s.confidence >= calibration.threshold for s in kept)


def _boundary_scores(model, episodes, tolerance: int) -> tuple[float, float]:
    """Boundary precision and F1 within ``tolerance`` of ``model``'s segmentation of ``episodes``."""
    counts = BoundaryCounts(0, 0, 0)
    for ep in episodes:
        pred = [s.end for s in segment_episode(model, ep)]
        truth = [s.end for s in ep.segments]
        counts += BoundaryCounts(match_boundaries(pred, truth, tolerance), len(pred), len(truth))
    return counts.precision, counts.f1


@pytest.mark.slow
def test_calibrated_end_bias_is_the_one_nearest_0_within_noise_of_the_best() -> None:
    model = tiny_ps_model(max_len=5, seed=4)
    episodes = [synthetic_episode(s, num_segments=4, max_seg_len=4) for s in range(4)]
    candidates = (-4.0, -2.0, 0.0, 2.0, 4.0)
    for tolerance in (0, 1):
        result = calibrate_end_bias(model, episodes, candidates, tolerance=tolerance)
        assert model.end_bias.item() == 0.0  # calibration alone does not change the model
        scores = {}
        for bias in candidates:  # the production path with the bias set: the calibration's choice wins
            model.end_bias.fill_(bias)
            scores[bias] = _boundary_scores(model, episodes, tolerance)
        model.end_bias.fill_(0.0)
        assert len(set(scores.values())) > 1  # the candidates really segment differently
        best = max(f1 for _, f1 in scores.values())
        # within one standard error of the best F1 (a proportion over the true boundaries), the bias
        # nearest 0; the production path's F1 at it is the one the calibration reports
        noise = math.sqrt(best * (1 - best) / result.num_boundaries)
        near_best = [b for b, (_, f1) in scores.items() if f1 >= best - noise - 1e-12]
        assert result.bias == min(near_best, key=lambda b: (abs(b), -b))
        assert result.f1 == pytest.approx(scores[result.bias][1])
        assert result.tolerance == tolerance and result.f1_without_bias == pytest.approx(scores[0.0][1])
        assert result.num_episodes == 4 and result.num_boundaries == sum(len(ep.segments) for ep in episodes)
    unannotated = Episode(
        "play-0", np.zeros((2, 1), np.float32), {CAMERA: np.zeros((3, 64, 64, 3), np.uint8)}
    )
    with pytest.raises(ValueError, match="annotated episodes"):
        calibrate_end_bias(model, [unannotated])


def test_a_sweep_within_its_noise_keeps_the_bias_nearest_0() -> None:
    # a small held-out split (69 boundaries): +2 wins by less than its standard error (0.059)
    sweep = {-1.0: 0.377, -0.25: 0.366, 0.0: 0.328, 1.0: 0.365, 2.0: 0.414, 3.0: 0.349}
    assert pick_end_bias(sweep, 69) == -0.25
    assert pick_end_bias(sweep, 10_000) == 2.0  # many boundaries: the best F1
    assert pick_end_bias({-0.5: 0.5, 0.5: 0.5, 1.0: 0.4}, 50) == 0.5  # a tie in distance: the higher


def test_calibrate_ps_model_sets_the_end_bias_and_records_both_calibrations() -> None:
    model = tiny_ps_model(max_len=5, seed=4)
    episodes = [synthetic_episode(s, num_segments=4, max_seg_len=4) for s in range(3)]
    record = calibrate_ps_model(model, episodes, target_accuracy=0.5)
    assert model.end_bias.item() == record["end_bias"]["bias"]
    assert record["calibration"]["num_segments"] == 12 and record["calibration"]["target_accuracy"] == 0.5
    assert record["own_cuts"]["threshold"] == record["calibration"]["threshold"]
    own = record["own_cuts_calibration"]
    assert own["target_accuracy"] == 0.5 and own["num_segments"] == record["own_cuts"]["segments"]


def test_majority_instruction_and_segment_probability() -> None:
    truth = [Segment(0, 3, "a"), Segment(5, 8, "b")]  # steps 3-4 and 8-9: no instruction
    cut = [Segment(0, 4, "a"), Segment(3, 7, "b"), Segment(6, 10, "b"), Segment(5, 6, "a")]
    # [3, 7): two unlabelled steps, then two of b: a tie goes to the earliest (none)
    assert majority_instructions(cut, truth, num_steps=10) == ["a", None, "b", "b"]
    assert segment_probability(Segment(0, 2, "a", 0.5, math.log(0.4))) == pytest.approx(0.2)
    assert segment_probability(Segment(0, 2, "a", 1.0, -800.0)) == 0.0  # a cut the model never makes


def test_own_cut_calibration_chooses_a_threshold_on_the_model_s_own_segmentation() -> None:
    model = tiny_ps_model(max_len=5, seed=4)
    episodes = [synthetic_episode(s, num_segments=4, max_seg_len=4) for s in range(3)]
    cuts = [segment_episode(model, episode) for episode in episodes]
    scores = [segment_probability(s) for cut in cuts for s in cut]
    right = [
        s.instruction == label
        for cut, episode in zip(cuts, episodes, strict=True)
        for s, label in zip(cut, majority_instructions(cut, episode.segments, episode.num_steps), strict=True)
    ]
    everything = calibrate_on_own_cuts(model, episodes, target_accuracy=1e-6)
    assert everything.num_segments == len(scores) and everything.coverage == 1.0
    assert everything.threshold == pytest.approx(min(scores))
    assert everything.accuracy_all == pytest.approx(np.mean(right))
    for target in (0.3, 0.6, 1.0):
        result = calibrate_on_own_cuts(model, episodes, target_accuracy=target)
        assert result.threshold == calibrate_threshold(scores, right, target)
        if math.isfinite(result.threshold):
            assert result.accuracy_kept >= target
    unannotated = [episode.with_segments([]) for episode in episodes]
    with pytest.raises(ValueError, match="annotated episodes"):
        calibrate_on_own_cuts(model, unannotated, target_accuracy=0.5)


def test_keep_rules_score_and_threshold_as_the_checkpoint_records_them() -> None:
    meta = {"calibration": {"threshold": 0.6}, "own_cuts_calibration": {"threshold": 0.3}}
    sure_label_bad_cut = Segment(0, 4, "a", 0.9, math.log(0.1))  # own-cut score 0.09
    sure_both = Segment(4, 8, "a", 0.7, math.log(0.5))  # 0.35
    unsure = Segment(8, 9, "b", 0.4, 0.0)  # 0.4
    segments = [sure_label_bad_cut, sure_both, unsure]
    label = KeepRule.of_checkpoint("label", meta, "m.pt")
    own = KeepRule.of_checkpoint("own_cuts", meta, "m.pt")
    assert (label.threshold, own.threshold) == (0.6, 0.3)
    assert [s for s in segments if label.keeps(s)] == [sure_label_bad_cut, sure_both]
    assert [s for s in segments if own.keeps(s)] == [sure_both, unsure]
    assert all(KeepRule.of_checkpoint("all", meta, "m.pt").keeps(s) for s in segments)
    assert own.describe() == "label x cut probability >= 0.300"
    assert own.to_json()["rule"] == "own_cuts"
    # A checkpoint with a label calibration only: one line naming it.
    assert KeepRule.of_checkpoint("label", {}, "old.pt").threshold == 0.0
    with pytest.raises(ValueError, match="old.pt: records no own-cut calibration"):
        KeepRule.of_checkpoint("own_cuts", {"calibration": {"threshold": 0.6}}, "old.pt")
    with pytest.raises(ValueError, match="keep rule must be one of label, own_cuts, all"):
        KeepRule("confident")


def test_steps_labelled_right_count_only_steps_the_truth_labels_the_same() -> None:
    truth = [Segment(0, 3, "a"), Segment(5, 8, "b")]  # steps 3-4 and 8-9: no instruction
    cut = [Segment(0, 4, "a"), Segment(4, 8, "b"), Segment(8, 10, "b"), Segment(0, 2, "b")]
    assert steps_labelled_right(cut, truth, num_steps=10) == [3, 3, 0, 0]


@pytest.mark.slow
def test_own_cuts_check_scores_what_the_threshold_keeps_of_the_model_s_segmentation() -> None:
    model = tiny_ps_model(max_len=5, seed=4)
    episodes = [synthetic_episode(s, num_segments=4, max_seg_len=4) for s in range(3)]
    everything = check_own_cuts(model, episodes, threshold=0.0)
    cuts = [segment_episode(model, episode) for episode in episodes]
    assert everything.segments == everything.kept == sum(len(cut) for cut in cuts)
    right = sum(
        sum(steps_labelled_right(c, e.segments, e.num_steps)) for c, e in zip(cuts, episodes, strict=True)
    )
    steps = sum(e.num_steps for e in episodes)  # the cuts tile every episode
    assert everything.kept_steps == steps
    assert everything.step_accuracy_all == everything.step_accuracy_kept == pytest.approx(right / steps)
    confidences = sorted(s.confidence for cut in cuts for s in cut)
    some = check_own_cuts(model, episodes, threshold=confidences[len(confidences) // 2])
    assert 0 < some.kept < some.segments and some.step_accuracy_all == everything.step_accuracy_all
    nothing = check_own_cuts(model, episodes, threshold=math.inf)
    assert nothing.kept == 0 and math.isnan(nothing.step_accuracy_kept)
    model.end_bias.fill_(4.0)  # cuts wherever it may
    short = check_own_cuts(model, episodes, threshold=0.0).segments
    model.cfg.min_len = 3  # cut as play is cut: with the model's L_min
    longer = check_own_cuts(model, episodes, threshold=0.0).segments
    assert longer == sum(len(segment_episode(model, e, min_len=3)) for e in episodes) < short


@pytest.mark.slow
def test_scoring_in_chunks_equals_scoring_at_once() -> None:
    """Long episodes are scored a chunk of windows at a time (bounded memory); the result is the same."""
    model = tiny_ps_model(max_len=5, seed=6, num_actions=3)
    episode = synthetic_episode(11, num_segments=12, max_seg_len=5)
    features = model.encode_episode(episode)
    torch.testing.assert_close(model.encode_episode(episode, chunk=4), features)
    whole = model.end_logits(features, chunk=episode.num_steps)
    for chunk in (1, 3, 7):
        torch.testing.assert_close(model.end_logits(features, chunk=chunk), whole, rtol=1e-5, atol=1e-5)
    spans = [(s.start, s.end) for s in episode.segments]
    one_by_one = torch.stack([model.label_logits(features, start, end) for start, end in spans])
    torch.testing.assert_close(
        model.segment_label_logits(features, spans, chunk=5), one_by_one, rtol=1e-5, atol=1e-5
    )
