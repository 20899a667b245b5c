"""Metrics: boundaries (exact, tolerant, without the final one), label accuracy, segment precision."""

from __future__ import annotations

import pytest

from playseg_core.data.episode import Segment
from playseg_core.ps.metrics import (
    BoundaryCounts,
    boundary_key,
    boundary_scores,
    evaluate,
    format_metrics_table,
    label_accuracy,
    match_boundaries,
    segment_matches,
)


def segs(*triples: tuple[int, int, str]) -> list[Segment]:
    return [Segment(start, end, instruction) for start, end, instruction in triples]


# Truth of a 10-step episode: ends 3, 7, 10.
TRUTH = segs((0, 3, "a"), (3, 7, "b"), (7, 10, "c"))


# --- boundaries --------------------------------------------------------------------------------------


def test_perfect_prediction_scores_one_everywhere():
    for tolerance in (0, 1, 2):
        for final in (True, False):
            counts = boundary_scores(TRUTH, TRUTH, tolerance, final, num_steps=10)
            assert (counts.precision, counts.recall, counts.f1) == (1.0, 1.0, 1.0)
    assert label_accuracy(TRUTH, TRUTH, 10).accuracy == 1.0
    assert (segment_matches(TRUTH, TRUTH).precision, segment_matches(TRUTH, TRUTH).recall) == (1.0, 1.0)


def test_empty_prediction_scores_zero():
    counts = boundary_scores([], TRUTH)
    assert counts == BoundaryCounts(matched=0, num_pred=0, num_truth=3)
    assert (counts.precision, counts.recall, counts.f1) == (0.0, 0.0, 0.0)
    assert label_accuracy([], TRUTH, 10).accuracy == 0.0
    assert segment_matches([], TRUTH).precision == 0.0


def test_off_by_one_is_missed_exactly_and_found_with_tolerance():
    pred = segs((0, 4, "a"), (4, 7, "b"), (7, 10, "c"))  # ends 4, 7, 10 against 3, 7, 10
    exact = boundary_scores(pred, TRUTH, tolerance=0)
    assert exact == BoundaryCounts(2, 3, 3)
    assert exact.f1 == pytest.approx(2 / 3)
    assert boundary_scores(pred, TRUTH, tolerance=1) == BoundaryCounts(3, 3, 3)
    far = segs((0, 5, "a"), (5, 7, "b"), (7, 10, "c"))  # end 5 is two steps from 3
    assert boundary_scores(far, TRUTH, tolerance=1).matched == 2
    assert boundary_scores(far, TRUTH, tolerance=2).matched == 3


def test_tolerant_matching_is_one_to_one():
    # Predicted ends 2 and 4 are both within +-1 of the true end 3: only one may match it.
    pred = segs((0, 2, "a"), (2, 4, "a"), (4, 10, "c"))
    counts = boundary_scores(pred, TRUTH, tolerance=1)
    assert counts == BoundaryCounts(2, 3, 3)  # 3<->2 or 4, and 10<->10; 7 unmatched
    # Greedy must not waste a match: 4->5 and 5->6 both fit within +-1 (a nearest-first rule gets 1).
    assert match_boundaries([4, 5], [5, 6], tolerance=1) == 2


def test_final_boundary_flag_drops_the_trivial_end():
    pred = segs((0, 5, "a"), (5, 10, "b"))  # ends 5, 10 against 3, 7, 10
    with_final = boundary_scores(pred, TRUTH, include_final=True, num_steps=10)
    without = boundary_scores(pred, TRUTH, include_final=False, num_steps=10)
    assert with_final == BoundaryCounts(1, 2, 3)  # only the trivial 10 matches
    assert without == BoundaryCounts(0, 1, 2)
    with pytest.raises(ValueError, match="num_steps"):
        boundary_scores(pred, TRUTH, include_final=False)


def test_label_accuracy_on_a_hand_made_example():
    # Truth covers steps 0..9 only partially: [0,3) "a", [5,9) "b"  -> 3 + 4 = 7 covered steps.
    truth = segs((0, 3, "a"), (5, 9, "b"))
    # Prediction: [0,2) "a", [2,6) "b", [6,8) "b"; steps 8, 9 uncovered.
    pred = segs((0, 2, "a"), (2, 6, "b"), (6, 8, "b"))
    # Steps 0,1: a==a correct. Step 2: b!=a wrong. Steps 5,6,7: b==b correct. Step 8: uncovered, wrong.
    # Steps 3, 4 and 9 are not covered by the truth and do not count. Correct 2 + 3 = 5 of 7.
    counts = label_accuracy(pred, truth, num_steps=10)
    assert (counts.correct, counts.total) == (5, 7)
    assert counts.accuracy == pytest.approx(5 / 7)


def test_segment_precision_needs_same_span_and_instruction():
    pred = segs((0, 3, "a"), (3, 7, "x"), (7, 9, "c"), (9, 10, "c"))
    # (0,3,a) matches; (3,7,x) has the wrong label; (7,9) and (9,10) have the wrong span.
    counts = segment_matches(pred, TRUTH)
    assert (counts.matched, counts.num_pred, counts.num_truth) == (1, 4, 3)
    assert (counts.precision, counts.recall) == (0.25, pytest.approx(1 / 3))


def test_bad_segments_are_rejected_naming_the_argument():
    overlapping = [Segment(0, 4), Segment(3, 6)]
    with pytest.raises(ValueError, match="pred"):
        boundary_scores(overlapping, TRUTH)
    with pytest.raises(ValueError, match="truth"):
        label_accuracy(TRUTH, [Segment(0, 12)], num_steps=10)
    with pytest.raises(TypeError, match="pred"):
        segment_matches([(0, 3)], TRUTH)
    with pytest.raises(ValueError, match="tolerance"):
        boundary_scores(TRUTH, TRUTH, tolerance=-1)


# --- evaluate ----------------------------------------------------------------------------------------


def test_evaluate_micro_averages_over_episodes():
    truth = {"e1": TRUTH, "e2": segs((0, 2, "a"), (2, 4, "b"))}
    pred = {
        "e1": segs((0, 4, "a"), (4, 7, "b"), (7, 10, "c")),  # ends 4, 7, 10: exact 2 of 3
        # e2 missing: empty prediction, 0 of 2 true boundaries.
    }
    results = evaluate(pred, truth, {"e1": 10, "e2": 4})
    assert results["episodes"] == 2
    assert (results["pred_segments"], results["true_segments"]) == (3, 5)
    # Exact: matched 2, predicted 3, true 5 (summed counts, not averaged ratios).
    assert results[boundary_key("precision", 0, True)] == pytest.approx(2 / 3)
    assert results[boundary_key("recall", 0, True)] == pytest.approx(2 / 5)
    assert results[boundary_key("f1", 0, True)] == pytest.approx(2 * (2 / 3) * (2 / 5) / (2 / 3 + 2 / 5))
    # Without final boundaries: e1 pred ends {4, 7} vs true {3, 7}; e2 true {2}: matched 1 of 2 and 3.
    assert results[boundary_key("precision", 0, False)] == pytest.approx(1 / 2)
    assert results[boundary_key("recall", 0, False)] == pytest.approx(1 / 3)
    assert results[boundary_key("recall", 1, False)] == pytest.approx(2 / 3)
    # Labels over 14 true steps: e1 step 3 is "a" instead of "b" -> 9 of 10 right; e2 0 of 4.
    assert (results["label_accuracy"], results["label_steps"]) == (pytest.approx(9 / 14), 14)
    # Segments: only (7, 10, "c") matches exactly.
    assert results["segment_precision"] == pytest.approx(1 / 3)
    assert results["segment_recall"] == pytest.approx(1 / 5)

    table = format_metrics_table(results)
    assert "+-2 steps, no final boundary" in table
    assert "0.667" in table and "0.643" in table


def test_evaluate_rejects_inconsistent_episode_sets():
    with pytest.raises(ValueError, match="pred_by_episode"):
        evaluate({"x": TRUTH}, {"e1": TRUTH}, {"e1": 10})
    with pytest.raises(ValueError, match="num_steps_by_episode"):
        evaluate({}, {"e1": TRUTH}, {})
    with pytest.raises(ValueError, match="'e1'.*truth"):
        evaluate({}, {"e1": TRUTH}, {"e1": 8})  # truth ends at 10 > 8 steps
