"""The baselines' parts on constructed inputs (cropping, top-1 selection, windows, metrics, the registry),
and the changepoint and random-window baselines on a synthetic task with clear boundaries.

The synthetic task (`synthetic_episode`, also used by test_baselines_models.py and test_baselines_cli.py):
a state whose first columns show the instruction being carried out (one-hot plus noise), one column
whose sign flips from one segment to the next and one with the progress through the segment (so a piece
of a segment can be told from a whole one); consecutive segments have different instructions.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from playseg_core.baselines.changepoint import CumulativeL2Cost, changepoints, step_signal
from playseg_core.baselines.common import (
    SegmentOptions,
    TrainingData,
    TrainOptions,
    covered_label_accuracy,
    fixed_windows,
)
from playseg_core.baselines.labelled_pieces import label_pieces
from playseg_core.baselines.random_windows import random_spans
from playseg_core.baselines.registry import METHODS, get_method, load_segmenter
from playseg_core.baselines.tridet import LevelOutput, TridetConfig, top1_detection
from playseg_core.baselines.unloc import crop_background
from playseg_core.checkpoint import CheckpointError
from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.ps.metrics import evaluate
from playseg_core.ps.model import save_model

torch.set_num_threads(1)

INSTRUCTIONS = ["open the drawer", "push the red block", "lift the blue block"]
FEATURES = Features.of(
    [
        Feature(STATE, "state", "float32", (6,)),
        Feature(ACTION, "action", "float32", (1,), num_values=3),
    ],
    fps=10.0,
)


def synthetic_episode(seed: int, steps: int = 60, lengths: tuple[int, int] = (3, 7)) -> Episode:
    """Segments of ``lengths`` steps up to about ``steps``; the state shows the instruction (columns
    0-2), a sign that flips at every boundary (column 3) and the progress through the segment, 0 at its
    first step and 1 at its last (column 4: a piece of a segment shows it is one); column 5 is noise;
    the action is mostly the instruction's index (80%), else random."""
    rng = np.random.default_rng(seed)
    bounds, labels = [0], []
    while bounds[-1] < steps:
        bounds.append(bounds[-1] + int(rng.integers(lengths[0], lengths[1] + 1)))
        choices = [k for k in range(len(INSTRUCTIONS)) if not labels or k != labels[-1]]
        labels.append(int(rng.choice(choices)))
    num_steps = bounds[-1]
    state = rng.normal(0.0, 0.1, size=(num_steps + 1, 6)).astype(np.float32)
    segments = []
    for index, ((start, end), label) in enumerate(
        zip(zip(bounds, bounds[1:], strict=False), labels, strict=True)
    ):
        state[start : end + (end == num_steps), label] += 1.0
        state[start : end + (end == num_steps), 3] += 1.0 if index % 2 else -1.0
        state[start:end, 4] += np.linspace(0.0, 1.0, end - start)
        segments.append(Segment(start, end, INSTRUCTIONS[label]))
    # Mostly the instruction's own action, sometimes another.
    typical = np.repeat(labels, np.diff(bounds))
    actions = np.where(rng.random(num_steps) < 0.8, typical, rng.integers(0, 3, num_steps))
    actions = actions.reshape(num_steps, 1).astype(np.float32)
    return Episode(f"synthetic-{seed}", actions, {}, state, segments)


def synthetic_data(train: int = 16, val: int = 4) -> TrainingData:
    return TrainingData(
        train=[synthetic_episode(s) for s in range(train)],
        val=[synthetic_episode(100 + s) for s in range(val)],
        instructions=list(INSTRUCTIONS),
        features=FEATURES,
    )


def scores(segmenter, episodes: list[Episode]) -> dict[str, float]:
    """Metrics of ``segmenter`` on ``episodes`` (ps.metrics.evaluate), plus the label accuracy over the
    steps its segments cover."""
    pred = {e.episode_id: segmenter.segment(e) for e in episodes}
    results = evaluate(
        pred, {e.episode_id: e.segments for e in episodes}, {e.episode_id: e.num_steps for e in episodes}
    )
    covered = [covered_label_accuracy(pred[e.episode_id], e.segments, e.num_steps) for e in episodes]
    results["covered_label_accuracy"] = sum(c.correct for c in covered) / max(
        1, sum(c.total for c in covered)
    )
    return results


# ----------------------------------------------------------------------------------------------------
# Constructed inputs


def test_cropping_keeps_one_class_run_long_enough() -> None:
    background = 9
    assert crop_background([9, 9, 2, 2, 2, 9], background, 1) == (2, 5, 2)
    # The paper's rule keeps a run that touches the window's edge; the closed rule (default) does not:
    # it may go on beyond the window, and no training window has one.
    assert crop_background([2, 2, 2], background, 3, closed=False) == (0, 3, 2)
    assert crop_background([9, 2, 2], background, 1, closed=False) == (1, 3, 2)
    assert crop_background([2, 2, 2], background, 3) is None
    assert crop_background([9, 2, 2], background, 1) is None
    assert crop_background([2, 2, 9], background, 1) is None
    assert crop_background([9, 2, 2, 9], background, 3) is None  # too short
    assert crop_background([9, 2, 1, 2, 9], background, 1) is None  # two classes remain
    assert crop_background([9, 2, 9, 2, 9], background, 1) is None  # background inside is not cropped
    assert crop_background([9, 9, 9], background, 1) is None  # nothing but background


def _level(
    stride: int, class_scores: list[list[float]], start_bins: list[int], end_bins: list[int]
) -> LevelOutput:
    """A level whose boundary distributions are certain: all mass on the given bins."""
    logits = torch.logit(torch.tensor([class_scores], dtype=torch.float64).clamp(1e-6, 1 - 1e-6))
    bins = 8

    def certain(chosen: list[int]) -> torch.Tensor:
        out = torch.full((1, len(chosen), bins + 1), -50.0, dtype=torch.float64)
        out[0, torch.arange(len(chosen)), torch.tensor(chosen)] = 50.0
        return out

    valid = torch.ones(1, len(class_scores), dtype=torch.bool)
    return LevelOutput(stride, valid, logits, certain(start_bins), certain(end_bins))


def test_top1_takes_the_best_cell_of_any_level_with_its_boundaries() -> None:
    fine = _level(1, [[0.1, 0.2], [0.3, 0.6], [0.1, 0.1], [0.2, 0.2]], [0, 1, 0, 0], [0, 2, 0, 0])
    coarse = _level(2, [[0.5, 0.1], [0.2, 0.9]], [0, 1], [0, 0])
    found = top1_detection([fine, coarse], 0, num_steps=4, min_len=1)
    # Coarse cell 1 (steps 2-3) scores 0.9 for class 1: start 1 stride before its left edge, end at its right.
    assert (found.start, found.end, found.label) == (0, 4, 1) and found.score == pytest.approx(0.9)
    found = top1_detection([fine], 0, num_steps=4, min_len=1)
    assert (found.start, found.end, found.label) == (0, 4, 1)  # cell 1: 1 bin left, 2 bins right
    assert top1_detection([fine], 0, num_steps=4, min_len=5) is None  # shorter than the minimum
    # A padded cell never wins, however high its score.
    coarse.valid[0, 1] = False
    found = top1_detection([coarse], 0, num_steps=4, min_len=1)
    assert (found.label, found.start, found.end) == (0, 0, 2)


def test_tridet_window_scales_with_the_segment_lengths() -> None:
    short = TridetConfig.for_lengths(21)
    assert (short.window, short.levels) == (32, 3)
    long = TridetConfig.for_lengths(100)
    assert long.window >= 125 and long.window % 2 ** (long.levels - 1) == 0
    assert long.num_bins * 2 ** (long.levels - 1) == long.window  # the top level's bins span the window
    assert [short.level_of(n) for n in (1, 4, 5, 8, 9, 30)] == [0, 0, 1, 1, 2, 2]


def test_windows_are_disjoint_and_inside_the_episode() -> None:
    rng = np.random.default_rng(0)
    for num_steps in (5, 32, 33, 100):
        windows = fixed_windows(num_steps, 32, rng)
        assert all(0 <= s < e <= num_steps for s, e in windows)
        assert all(a[1] <= b[0] for a, b in zip(windows, windows[1:], strict=False))
        assert all(e - s == min(32, num_steps) for s, e in windows)
    spans = random_spans(100, 2, 9, rng)
    assert spans[0][0] == 0 and spans[-1][1] == 100
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:], strict=False))
    assert all(2 <= e - s <= 9 for s, e in spans[:-1])
    with pytest.raises(ValueError, match="shortest <= longest"):
        random_spans(10, 5, 4, rng)


def test_covered_label_accuracy_counts_only_the_covered_steps() -> None:
    truth = [Segment(0, 4, "a"), Segment(4, 10, "b")]
    pred = [Segment(2, 6, "a")]  # steps 2, 3 right; 4, 5 wrong
    counts = covered_label_accuracy(pred, truth, 10)
    assert (counts.correct, counts.total) == (2, 4)
    assert covered_label_accuracy([], truth, 10).total == 0


def test_cumulative_cost_equals_the_direct_l2_cost() -> None:
    signal = np.random.default_rng(0).normal(size=(30, 4))
    cost = CumulativeL2Cost().fit(signal)
    for start, end in [(0, 30), (3, 9), (10, 11)]:
        piece = signal[start:end]
        assert cost.error(start, end) == pytest.approx(float(np.square(piece - piece.mean(0)).sum()))
    steps = np.concatenate([np.zeros((10, 2)), np.ones((7, 2)) * 5, np.zeros((8, 2))])
    assert changepoints(steps, penalty=1.0) == [(0, 10), (10, 17), (17, 25)]


def test_the_registry_names_every_method_and_refuses_unknown_ones(tmp_path: Path) -> None:
    assert list(METHODS) == ["ps", "unloc", "tridet", "random", "changepoint"]
    assert [m.name for m in METHODS.values() if not m.tiles] == ["unloc", "tridet"]
    with pytest.raises(
        ValueError, match="--method 'crf': unknown segmentation method 'crf' \\(known: ps, unloc"
    ):
        get_method("crf")
    with pytest.raises(CheckpointError, match="nothing.pt: no such file"):
        load_segmenter("tridet", tmp_path / "nothing.pt")


# ----------------------------------------------------------------------------------------------------
# The labelling-model baselines learn the synthetic task


@pytest.fixture(scope="module")
def trained_changepoint():
    return get_method("changepoint").train(synthetic_data(), TrainOptions(max_steps=300, batch_size=16))


@pytest.mark.slow
def test_changepoint_pieces_find_the_synthetic_boundaries(trained_changepoint, tmp_path: Path) -> None:
    test = [synthetic_episode(200 + s) for s in range(6)]
    signal = step_signal(test[0], FEATURES, "state_action")
    assert signal.shape == (test[0].num_steps, 6 + 3)  # the state and the one-hot action
    results = scores(trained_changepoint.segmenter, test)
    assert results["segment_precision"] >= 0.9, results
    assert results["boundary_recall_tol0"] >= 0.9 and results["label_accuracy"] >= 0.9, results
    path = trained_changepoint.save(tmp_path / "cp.pt", {})
    loaded = load_segmenter("changepoint", path, SegmentOptions())
    assert [loaded.segment(e) for e in test[:2]] == [
        trained_changepoint.segmenter.segment(e) for e in test[:2]
    ]
    with pytest.raises(CheckpointError, match="cp.pt: a 'labeller' checkpoint, expected tridet"):
        load_segmenter("tridet", path)
    plain = save_model(tmp_path / "plain.pt", trained_changepoint.segmenter.model, {})
    with pytest.raises(ValueError, match="plain.pt: no changepoint settings"):
        load_segmenter("changepoint", plain)


@pytest.mark.slow
def test_random_windows_tile_with_annotated_lengths_and_labelled_well(tmp_path: Path) -> None:
    trained = get_method("random").train(synthetic_data(), TrainOptions(max_steps=300, batch_size=16))
    path = trained.save(tmp_path / "random.pt", {})
    segmenter = load_segmenter("random", path, SegmentOptions(seed=3))
    test = [synthetic_episode(200 + s) for s in range(6)]
    for episode in test:
        segments = segmenter.segment(episode)
        assert segments[0].start == 0 and segments[-1].end == episode.num_steps
        assert all(3 <= s.length <= 7 for s in segments[:-1])
    results = scores(segmenter, test)
    # The labelling model learnt the task: the true segments, relabelled, get their labels ...
    relabelled = {
        e.episode_id: label_pieces(segmenter.model, e, [(s.start, s.end) for s in e.segments]) for e in test
    }
    truth = {e.episode_id: e.segments for e in test}
    relabel_results = evaluate(relabelled, truth, {e.episode_id: e.num_steps for e in test})
    assert relabel_results["segment_precision"] >= 0.95, relabel_results
    # ... but random cuts rarely hit a true segment, and a window across two segments has one label.
    assert results["segment_precision"] < 0.3 and 0.5 <= results["label_accuracy"] < 0.9, results
    # Another seed, other windows; the same seed, the same windows.
    assert segmenter.segment(test[0]) == load_segmenter("random", path, SegmentOptions(seed=3)).segment(
        test[0]
    )
    assert segmenter.segment(test[0]) != load_segmenter("random", path, SegmentOptions(seed=4)).segment(
        test[0]
    )


def test_ps_trains_and_segments_through_the_registry(tmp_path: Path) -> None:
    """One epoch: the plumbing (the CLI's PS path is offline.py's own, tested elsewhere)."""
    trained = get_method("ps").train(
        synthetic_data(train=6, val=2), TrainOptions(epochs=1, label_accuracy=0.5)
    )
    path = trained.save(tmp_path / "ps.pt", {"note": 1})
    assert torch.load(path, weights_only=True)["meta"]["calibration"]["target_accuracy"] == 0.5
    with pytest.raises(ValueError, match="label accuracy target must be in \\(0, 1\\], got 0"):
        TrainOptions(label_accuracy=0)
    segmenter = load_segmenter("ps", path, SegmentOptions(min_len=2))
    episode = synthetic_episode(200)
    segments = segmenter.segment(episode)
    assert segments[0].start == 0 and segments[-1].end == episode.num_steps
    assert all(s.length >= 2 for s in segments) and segmenter.tiles
    assert segmenter.label_threshold == trained.segmenter.label_threshold


# ----------------------------------------------------------------------------------------------------
# Every method trains through the one loop (training/loop.py), within the options' budget


class _LoopSpy:
    """Wraps training/loop.py `train_loop` where the methods call it (the window models' `fit`, PS and
    the labelling model's `_fit`), recording each run's task name, config and result; also counts the
    optimizer steps actually taken, whoever takes them."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from torch.optim.optimizer import register_optimizer_step_post_hook

        from playseg_core.training import loop

        self.runs: list[tuple[str, object, object]] = []
        self.optimizer_steps = 0

        def spy(task, cfg):
            result = loop.train_loop(task, cfg)
            self.runs.append((task.name, cfg, result))
            return result

        def count(*_) -> None:
            self.optimizer_steps += 1

        monkeypatch.setattr("playseg_core.baselines.common.train_loop", spy)
        monkeypatch.setattr("playseg_core.ps.training.train_loop", spy)
        self._hook = register_optimizer_step_post_hook(count)

    def close(self) -> None:
        self._hook.remove()


@pytest.fixture
def loop_spy(monkeypatch: pytest.MonkeyPatch):
    spy = _LoopSpy(monkeypatch)
    yield spy
    spy.close()


LOOP_NAMES = {
    "ps": "ps",
    "unloc": "unloc",
    "tridet": "tridet",
    "random": "labeller",
    "changepoint": "labeller",
}


@pytest.mark.slow
@pytest.mark.parametrize("method", list(METHODS))
def test_every_method_trains_through_the_loop_within_max_steps_and_max_minutes(method: str, loop_spy) -> None:
    data = synthetic_data(train=6, val=2)
    get_method(method).train(data, TrainOptions(max_steps=3, batch_size=8, device="cpu"))
    assert loop_spy.optimizer_steps == 3  # exactly the cap: no other loop took a step
    [(name, cfg, result)] = loop_spy.runs
    assert name == LOOP_NAMES[method] and cfg.steps == 3 and cfg.device == torch.device("cpu")
    assert (result.steps, result.stopped) == (3, "step cap")
    # max_minutes ends the run after the step that runs out of time (here: the first), as the loop says
    loop_spy.runs.clear()
    loop_spy.optimizer_steps = 0
    get_method(method).train(data, TrainOptions(max_steps=50, max_minutes=1e-9, batch_size=8))
    [(name, cfg, result)] = loop_spy.runs
    assert cfg.max_minutes == 1e-9 and (result.steps, result.stopped) == (1, "max minutes")
    assert loop_spy.optimizer_steps == 1


def test_the_window_models_budget_defaults_and_options(loop_spy) -> None:
    from playseg_core.baselines.common import WINDOW_EVAL_EVERY, WINDOW_PATIENCE, WINDOW_STEP_CAP
    from playseg_core.baselines.unloc import UnlocConfig, train_unloc
    from playseg_core.training.device import DeviceError

    data = synthetic_data(train=4, val=2)
    options = TrainOptions(max_minutes=1e-9)  # the defaults, stopped after one step
    trained = train_unloc(data, options, UnlocConfig(dim=16))
    (_, cfg, result), *_ = loop_spy.runs
    assert (cfg.steps, cfg.eval_every, cfg.patience) == (WINDOW_STEP_CAP, WINDOW_EVAL_EVERY, WINDOW_PATIENCE)
    assert "1 of at most 2000 steps, stopped by max minutes; kept step 1" in trained.report
    # epochs: a fixed budget (ceil(segments / batch) steps each), no early stopping
    segments = sum(len(e.segments) for e in data.train)
    train_unloc(data, TrainOptions(epochs=2, batch_size=16, patience=3), UnlocConfig(dim=16))
    _, cfg, result = loop_spy.runs[-1]
    assert (cfg.steps, cfg.patience, result.steps) == (2 * -(-segments // 16), 0, cfg.steps)
    train_unloc(data, TrainOptions(max_steps=4, eval_every=2, patience=7), UnlocConfig(dim=16))
    _, cfg, result = loop_spy.runs[-1]
    assert (cfg.steps, cfg.eval_every, cfg.patience) == (4, 2, 7)
    assert [entry["step"] for entry in result.history] == [2.0, 4.0]
    with pytest.raises(ValueError, match="max_steps must be at least 1, got 0"):
        TrainOptions(max_steps=0)
    with pytest.raises(ValueError, match="patience must be 0"):
        TrainOptions(patience=-1)
    with pytest.raises(ValueError, match="max_minutes must be a positive number"):
        TrainOptions(max_minutes=0)
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="no CUDA device"):
            train_unloc(data, TrainOptions(max_steps=1, device="cuda"), UnlocConfig(dim=16))


def test_the_ps_budget_options_reach_its_train_config() -> None:
    from playseg_core.baselines.common import ps_training_setup

    data = synthetic_data(train=4, val=2)
    _, cfg, _ = ps_training_setup(data, TrainOptions())
    assert (cfg.epochs, cfg.max_steps, cfg.max_minutes, cfg.device) == (None, None, None, "auto")
    given = TrainOptions(
        max_steps=7, max_minutes=2.5, patience=3, eval_every=5, device="cpu", batch_size=4, lr=0.01, epochs=2
    )
    _, cfg, _ = ps_training_setup(data, given)
    assert (cfg.max_steps, cfg.max_minutes, cfg.patience, cfg.eval_every) == (7, 2.5, 3, 5)
    assert (cfg.device, cfg.segments_per_batch, cfg.lr, cfg.epochs) == ("cpu", 4, 0.01, 2)


def test_a_window_batch_is_a_function_of_its_step_alone() -> None:
    """The loop may ask a step again (a resumed run): the s-th draw of the seed's stream, as a loop
    drawing step after step from one generator gets."""
    from playseg_core.baselines.common import WindowBatches, _DrawnBatches

    batches = WindowBatches(lambda rng, training: rng.integers(0, 1000, size=3), lambda w: w.tolist(), None)
    stream = np.random.default_rng(5)
    expected = [stream.integers(0, 1000, size=3).tolist() for _ in range(8)]
    batch_at = _DrawnBatches(5, batches)
    assert [batch_at(s) for s in (0, 1, 2)] == expected[:3]
    assert [batch_at(s) for s in (6, 7, 1, 2)] == [expected[6], expected[7], expected[1], expected[2]]


def _fit_before_the_loop(task, cfg, seed: int, lr: float):
    """The window models' training loop as it was before training/loop.py (common.py `fit`, verbatim
    but for taking the batches from the task's `WindowBatches`): AdamW + LambdaLR warm-up/cosine, clip
    5, the val loss of 4 fixed batches at the end."""
    from playseg_core.training.loop import LoopResult

    batches, model, steps = task.batch_at.batches, task.model, cfg.steps
    rng = np.random.default_rng(seed)
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    warmup = max(1, steps // 20)

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        return 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, steps - warmup)))

    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
    model.train()
    for step in range(steps):
        # the loop sets each step's rate from the task: the very same numbers as this schedule
        assert optimizer.param_groups[0]["lr"] == task.learning_rate(step), step
        loss = batches.loss(model, batches.build(batches.choose(rng, True)))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        optimizer.step()
        schedule.step()
    model.eval()
    val_rng = np.random.default_rng(12345)
    with torch.no_grad():
        val = [float(batches.loss(model, batches.build(batches.choose(val_rng, False)))) for _ in range(4)]
    best = {"step": float(steps), "val_loss": float(np.mean(val)), "train_loss": 0.0}
    return LoopResult(model, steps, steps, "step cap", steps, best, [best], 0.0, "val_loss")


@pytest.mark.slow
@pytest.mark.parametrize("method", ["unloc", "tridet"])
def test_without_early_stopping_the_window_models_train_as_before_the_loop(
    method: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The same steps with early stopping off (patience 0, one evaluation at the end): the CPU weights
    and val loss are bit for bit those of the window models' former loop (`_fit_before_the_loop`; also
    checked once against the former code itself: the same weights after 40 steps of either model)."""
    from playseg_core.baselines.tridet import TridetConfig, train_tridet
    from playseg_core.baselines.unloc import UnlocConfig, train_unloc
    from playseg_core.checkpoint import read_checkpoint

    def train(options: TrainOptions, path: Path):
        data = synthetic_data(train=6, val=2)
        data.bounds = {"k_max": 3}
        if method == "unloc":
            trained = train_unloc(data, options, UnlocConfig(dim=16))
        else:
            cfg = TridetConfig.for_lengths(7)
            cfg.dim = 16
            trained = train_tridet(data, options, cfg)
        checkpoint = read_checkpoint(trained.save(path, {}), (method,))
        return checkpoint.state_dict, checkpoint.meta

    options = TrainOptions(seed=2, max_steps=30, patience=0, eval_every=30, batch_size=8, lr=3e-3)
    weights, meta = train(options, tmp_path / "loop.pt")
    assert (meta["steps"], meta["stopped"], meta["best_step"]) == (30, "step cap", 30)
    monkeypatch.setattr(
        "playseg_core.baselines.common.train_loop",
        lambda task, cfg: _fit_before_the_loop(task, cfg, seed=2, lr=3e-3),
    )
    before, meta_before = train(options, tmp_path / "before.pt")
    assert weights.keys() == before.keys()
    assert [key for key in weights if not torch.equal(weights[key], before[key])] == []
    assert meta["val_loss"] == meta_before["val_loss"]


@pytest.mark.parametrize("method", ["unloc", "tridet"])
def test_the_window_models_build_their_batches_through_the_fixed_feature_cache(
    method: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """UnLoc and TriDet hand every batch's windows to `window_inputs` with one `FixedFeatureCache` of
    their encoders (what spares a camera encoder that learns nothing from running in every batch: the
    cached rows themselves are checked in tests/test_tabletop_symmetry.py)."""
    import importlib

    from playseg_core.baselines import common
    from playseg_core.ps.fixed_features import FixedFeatureCache

    module = importlib.import_module(f"playseg_core.baselines.{method}")
    caches = []

    def spy(encoders, items, fixed=None):
        caches.append(fixed)
        return common.window_inputs(encoders, items, fixed)

    monkeypatch.setattr(module, "window_inputs", spy)
    get_method(method).train(synthetic_data(train=4, val=2), TrainOptions(max_steps=2, batch_size=4))
    assert len(caches) > 2  # the val batches and one per step
    assert all(isinstance(cache, FixedFeatureCache) for cache in caches) and len({id(c) for c in caches}) == 1
