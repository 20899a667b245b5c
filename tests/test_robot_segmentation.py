"""Robot-shaped data: cameras of any size, a state vector, continuous actions. The generic step encoders
read each; a model that reads the feature where the boundaries show finds them, one without it does not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from playseg_core.data.dataset import DatasetWriter, PlayDataset
from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, STATE, Feature, Features
from playseg_core.ps.encoders import EncoderSpec, choose_encoders, feature_statistics
from playseg_core.ps.model import PERIODIC_FREQUENCIES, TRUNK_DROPOUT, ModelConfig, PSModel, load_model
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds, train_ps
from playseg_ros.cli import main as cli_main

torch.set_num_threads(1)

FRONT, WRIST = "observation.images.front", "observation.images.wrist"
INSTRUCTIONS = ("reach", "push")


def robot_features(cameras: dict[str, tuple[int, int]], state: bool) -> Features:
    features = [Feature(name, "image", "uint8", (h, w, 3)) for name, (h, w) in cameras.items()]
    if state:
        features.append(Feature(STATE, "state", "float32", (7,), names=tuple(f"joint_{i}" for i in range(7))))
    features.append(Feature(ACTION, "action", "float32", (7,), low=(-1.0,) * 7, high=(1.0,) * 7))
    return Features.of(features, fps=10.0)


def robot_episode(seed: int, features: Features, ends_in: str, lengths: tuple[int, int] = (6, 12)) -> Episode:
    """Uninformative camera noise; the segment ends show only in the actions (``ends_in="action"``: the
    last action of a segment is a large command) or only in the state (``"state"``: a gripper joint is
    1 at the observation that ends a segment). The instruction alternates, visible in the state's last
    joint (and nowhere else)."""
    rng = np.random.default_rng(seed)
    bounds = [0]
    while bounds[-1] < 80:
        bounds.append(bounds[-1] + int(rng.integers(lengths[0], lengths[1] + 1)))
    num_steps = bounds[-1]
    images = {
        name: rng.integers(0, 256, size=(num_steps + 1, *features[name].shape), dtype=np.uint8)
        for name in features.cameras
    }
    actions = rng.normal(0.0, 0.2, size=(num_steps, 7)).astype(np.float32)
    state = rng.normal(0.0, 0.2, size=(num_steps + 1, 7)).astype(np.float32)
    segments = []
    for k, (start, end) in enumerate(zip(bounds, bounds[1:], strict=False)):
        label = INSTRUCTIONS[(seed + k) % 2]
        state[start + 1 : end + 1, 6] = 1.0 if label == "push" else -1.0
        if ends_in == "action":
            actions[end - 1] = 3.0
        else:
            state[end, 0] = 3.0
        segments.append(Segment(start, end, label))
    return Episode(f"robot-{seed}", actions, images, state if features.state else None, segments)


def _boundaries(model, episodes: list[Episode]) -> tuple[float, float]:
    hits = predicted = true = 0
    for episode in episodes:
        pred = {s.end for s in segment_episode(model, episode, min_len=model.cfg.min_len)}
        truth = {s.end for s in episode.segments}
        hits, predicted, true = hits + len(pred & truth), predicted + len(pred), true + len(truth)
    return hits / predicted, hits / true


def _model_config(features: Features, episodes: list[Episode], **config) -> ModelConfig:
    """The default generic model for ``features``, with the bounds and statistics of ``episodes``."""
    bounds = segment_bounds(episodes)
    return model_config_for(
        features,
        None,
        len(INSTRUCTIONS),
        max_len=bounds.max_len,
        episodes=episodes,
        min_len=bounds.min_len,
        **config,
    )


def _train(features: Features, train: list[Episode], val: list[Episode], **config) -> object:
    bounds = segment_bounds(train)
    model_cfg = _model_config(features, train, **config)
    cfg = TrainConfig(epochs=12, segments_per_batch=8, k_max=bounds.k_max, progress=False, log_epochs=False)
    return train_ps(train, val, INSTRUCTIONS, cfg, model_cfg).model


@pytest.mark.slow
@pytest.mark.parametrize("ends_in", ["action", "state"])
def test_boundaries_that_only_one_feature_shows_are_found_by_the_model_that_reads_it(ends_in: str) -> None:
    features = robot_features({FRONT: (12, 16)}, state=True)
    train = [robot_episode(s, features, ends_in) for s in range(12)]
    val = [robot_episode(100 + s, features, ends_in) for s in range(4)]
    test = [robot_episode(200 + s, features, ends_in) for s in range(4)]
    reads = _train(features, train, val)
    assert [s.kind for s in reads.cfg.encoders] == ["image_cnn", "state_mlp", "continuous_action"]
    precision, recall = _boundaries(reads, test)
    assert precision >= 0.9 and recall >= 0.9, (precision, recall)
    blind_config = {"read_actions": False} if ends_in == "action" else {"overrides": {STATE: "none"}}
    blind = _train(features, train, val, **blind_config)
    assert ends_in[:5] not in " ".join(s.kind for s in blind.cfg.encoders)
    blind_precision, blind_recall = _boundaries(blind, test)
    assert blind_precision + blind_recall < precision + recall - 0.4, (blind_precision, blind_recall)


def test_bounds_and_statistics_come_from_the_annotated_data() -> None:
    features = robot_features({FRONT: (12, 16)}, state=True)
    episodes = [robot_episode(s, features, "action", lengths=(20, 40)) for s in range(3)]
    lengths = [seg.length for ep in episodes for seg in ep.segments]
    bounds = segment_bounds(episodes)
    assert bounds.max_len == int(np.ceil(1.25 * max(lengths))) > max(lengths)
    assert bounds.min_len == min(lengths) // 2 and bounds.k_max == round(0.25 * float(np.median(lengths)))
    assert segment_bounds(episodes, max_len=128, k_max=3).max_len == 128
    assert segment_bounds(episodes, domain="babyai").max_len == 25  # the domain's measured setting
    stats = feature_statistics(episodes, [STATE, ACTION])
    all_actions = np.concatenate([ep.actions for ep in episodes])
    np.testing.assert_allclose(stats[ACTION]["mean"], all_actions.mean(0), atol=1e-5)
    np.testing.assert_allclose(stats[ACTION]["std"], all_actions.std(0), atol=1e-5)


def test_a_robots_model_reads_its_state_as_measured_values_and_drops_out_in_training_only() -> None:
    features = robot_features({FRONT: (12, 16)}, state=True)
    episodes = [robot_episode(s, features, "state") for s in range(2)]
    config = model_config_for(features, None, len(INSTRUCTIONS), episodes=episodes)
    assert config.trunk.periodic_frequencies == PERIODIC_FREQUENCIES > 0
    model = PSModel(config, INSTRUCTIONS).eval()
    # the camera's encoder learns: of the step features, only the state's values are measured
    size = features[STATE].size
    first = model.encoders.encoders[0].out_dim
    assert model.encoders.measured_columns == list(range(first, first + size))
    assert model.trunk.periodic is not None
    # the trunk's dropout acts in training only: segmenting is deterministic
    assert config.trunk.dropout == TRUNK_DROPOUT > 0
    features_of_steps = model.encode_episode(episodes[0]).detach()
    with torch.no_grad():
        assert torch.equal(model.end_logits(features_of_steps), model.end_logits(features_of_steps))
        windows = features_of_steps[None, :10]
        model.train()
        assert not torch.equal(model.trunk(windows), model.trunk(windows))
        model.eval()
    # a domain that names the generic kind with settings of its own gets the statistics too
    spec = choose_encoders(
        features,
        lambda f: {STATE: EncoderSpec("state_mlp", STATE, {"hidden": 32})},
        feature_statistics(episodes, [STATE, ACTION]),
    )[1]
    assert spec.config["hidden"] == 32 and len(spec.config["mean"]) == size


@pytest.mark.slow
def test_a_robot_dataset_goes_through_train_segment_evaluate(tmp_path: Path, capsys) -> None:
    """Two cameras of different sizes, a 7-D state, 7-D continuous actions, L_max over 100."""
    features = robot_features({FRONT: (24, 32), WRIST: (16, 16)}, state=True)
    data = tmp_path / "robot"
    with DatasetWriter(data, INSTRUCTIONS, features=features) as writer:
        for seed in range(10):
            split = "train" if seed < 6 else "val" if seed < 8 else "test"
            writer.add(robot_episode(seed, features, "action", lengths=(40, 90)), split)
    model = tmp_path / "ps.pt"
    assert cli_main(["train", "--data", str(data), "--out", str(model), "--epochs", "1"]) == 0
    printed = capsys.readouterr().out
    assert (
        f"{FRONT} (image_cnn), {WRIST} (image_cnn), {STATE} (state_mlp), {ACTION} (continuous_action)"
        in printed
    )
    loaded, _ = load_model(model)
    assert loaded.max_len >= 100 and loaded.cfg.min_len >= 20
    out = tmp_path / "seg"
    argv = ["segment", "--model", str(model), "--input", str(data), "--splits", "test", "--out", str(out)]
    assert cli_main(argv) == 0
    segmented = PlayDataset.open(out)
    assert segmented.features == PlayDataset.open(data).features and len(segmented) == 2
    for index in range(len(segmented)):
        segments = segmented.segments(index, truth=True)
        assert segments and all(loaded.cfg.min_len <= s.length <= loaded.max_len for s in segments)
    assert cli_main(["evaluate", "--pred", str(out), "--truth", str(data), "--plot-episodes", "0"]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("end_lookahead", [0, 2])
def test_the_stream_equals_offline_segmentation_on_robot_data(end_lookahead: int) -> None:
    """Two cameras, a state and continuous actions, pushed one step at a time as a live segmenter does;
    with an end head reading 2 steps past each end, each end is decided 2 steps later, same result."""
    features = robot_features({FRONT: (12, 16), WRIST: (8, 8)}, state=True)
    episodes = [robot_episode(s, features, "action") for s in range(3)]
    torch.manual_seed(1)  # untrained: many arbitrary cuts to compare
    model = PSModel(_model_config(features, episodes, end_lookahead=end_lookahead), list(INSTRUCTIONS))
    episode = episodes[0]
    stream, live = StreamingSegmenter(model), []
    for t in range(episode.num_steps + 1):
        observation = {name: frames[t] for name, frames in episode.images.items()} | {STATE: episode.state[t]}
        live += stream.push(observation, episode.actions[t] if t < episode.num_steps else None)
    live += stream.finish()
    offline = segment_episode(model, episode)
    assert len(offline) > 1
    assert [(s.start, s.end, s.instruction) for s in live] == [
        (s.start, s.end, s.instruction) for s in offline
    ]
