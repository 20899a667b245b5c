"""PS model: the end matrix and the online column agree, the trunk is causal from the start, checkpoints."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from playseg_core.checkpoint import CheckpointError
from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import ACTION, Feature, FeatureError, Features, check_discrete_actions
from playseg_core.domains.babyai.encoder import GridTileConfig, grid_tile_spec
from playseg_core.domains.babyai.spec import CAMERA
from playseg_core.ps.encoders import EncoderSpec, as_tensors
from playseg_core.ps.model import LabelModel, ModelConfig, PSModel, TrunkConfig, load_model, save_model

torch.set_num_threads(1)

NUM_CLASSES = 4
NUM_ACTIONS = 3  # the synthetic episodes' actions: 0, 1, 2
INSTRUCTIONS = [f"go to thing {c}" for c in range(NUM_CLASSES)]
FEATURES = Features.of(
    [
        Feature(CAMERA, "image", "uint8", (64, 64, 3)),
        Feature(ACTION, "action", "float32", (1,), num_values=NUM_ACTIONS),
    ]
)


def tiny_model_config(
    max_len: int = 6, num_actions: int = 0, num_layers: int = 2, size: int = 64, end_lookahead: int = 0
) -> ModelConfig:
    """A small grid-tile model for ``size``-pixel frames; with ``num_actions`` it also reads the previous
    action (4-d embedding); its end head reads ``end_lookahead`` steps past an end."""
    features = FEATURES.with_camera(Feature(CAMERA, "image", "uint8", (size, size, 3)))
    encoders = [
        grid_tile_spec(features[CAMERA], GridTileConfig(tile_channels=8, object_dim=8, feature_dim=16))
    ]
    if num_actions:
        features = features.with_action(Feature(ACTION, "action", "float32", (1,), num_values=num_actions))
        encoders.append(EncoderSpec("discrete_action", ACTION, {"dim": 4}))
    trunk = TrunkConfig(hidden_dim=16, num_layers=num_layers, kernel_size=3, max_len=max_len)
    return ModelConfig(encoders, features, NUM_CLASSES, trunk, end_lookahead=end_lookahead)


def tiny_ps_model(max_len: int = 6, seed: int = 0, num_actions: int = 0, end_lookahead: int = 0) -> PSModel:
    torch.manual_seed(seed)
    return PSModel(tiny_model_config(max_len, num_actions, end_lookahead=end_lookahead), INSTRUCTIONS).eval()


def encode_frames(model: PSModel, frames: np.ndarray) -> torch.Tensor:
    """The camera encoder alone (no action columns)."""
    return model.encoders.encoders[0](torch.from_numpy(np.ascontiguousarray(frames)))


PALETTE = np.array([[230, 40, 40], [40, 230, 40], [40, 40, 230], [230, 230, 40]], np.uint8)


def synthetic_episode(
    seed: int,
    num_segments: int = 6,
    max_seg_len: int = 5,
    size: int = 64,
    ends_in_actions: bool = False,
    starts_in_actions: bool = False,
) -> Episode:
    """Play-like frames of 8x8 tiles: the top-left tile in the colour of the current instruction's
    class, a marker tile at every segment end, and a flickering tile so that frames differ.

    With `ends_in_actions`, only the actions show where segments end: one class for the whole episode,
    no marker, every segment's last action 2 and the others 0 or 1. With `starts_in_actions`, the same
    but every segment's *first* action is 2: an end shows only in the action after it.
    """
    ends_in_actions = ends_in_actions or starts_in_actions
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, max_seg_len + 1, size=num_segments)
    classes = rng.integers(0, NUM_CLASSES, size=num_segments)
    if ends_in_actions:
        classes[:] = classes[0]
    num_steps = int(lengths.sum())
    frames = np.zeros((num_steps + 1, size, size, 3), np.uint8)
    segments, start = [], 0
    for length, cls in zip(lengths.tolist(), classes.tolist(), strict=True):
        end = start + length
        frames[start + 1 : end + 1, :8, :8] = PALETTE[cls]
        if not ends_in_actions:
            frames[end, 8:16, 8:16] = 255  # the "goal reached" marker
        segments.append(Segment(start, end, INSTRUCTIONS[cls]))
        start = end
    frames[:, :8, 8:16, 1] = rng.integers(0, 120, size=(num_steps + 1, 1, 1), dtype=np.uint8)
    actions = rng.integers(0, 3, size=(num_steps, 1)).astype(np.float32)
    if ends_in_actions:
        frames[0, :8, :8] = PALETTE[classes[0]]
        actions = rng.integers(0, 2, size=(num_steps, 1)).astype(np.float32)
        actions[[seg.start if starts_in_actions else seg.end - 1 for seg in segments]] = 2
    return Episode(f"synthetic-{seed}", actions, {CAMERA: frames}, segments=segments)


class UnsafePayload:
    """An arbitrary pickled object: weights_only loading must refuse it."""


def random_features(num_frames: int, dim: int = 16, seed: int = 1) -> torch.Tensor:
    return torch.randn(num_frames, dim, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize(
    ("num_steps", "num_actions", "lookahead"),
    [(3, 0, 0), (6, 0, 0), (14, 0, 0), (14, 3, 0), (3, 0, 2), (14, 3, 2)],
)
def test_end_column_equals_diagonal_of_end_logits(num_steps: int, num_actions: int, lookahead: int) -> None:
    model = tiny_ps_model(max_len=6, num_actions=num_actions, end_lookahead=lookahead)
    features = random_features(num_steps + 1, dim=model.step_dim)
    # past the last observation the lookahead reads zero rows, as the matrix's padding
    padded = torch.cat([features, features.new_zeros(lookahead, features.shape[1])])
    with torch.no_grad():
        matrix = model.end_logits(features)
        assert matrix.shape == (num_steps, 6)
        for t in range(1, num_steps + 1):
            window = padded[max(0, t - model.max_len) : t + 1 + lookahead]
            column = model.end_column(window, starts_episode=t <= model.max_len)
            for k in range(model.max_len):
                if t - k - 1 >= 0:
                    torch.testing.assert_close(column[k], matrix[t - k - 1, k], rtol=1e-5, atol=1e-5)
                else:
                    assert column[k] == float("-inf")


def test_output_k_ignores_frames_after_position_k() -> None:
    model = tiny_ps_model(max_len=6)
    frames = synthetic_episode(3).images[CAMERA]
    with torch.no_grad():
        features = encode_frames(model, frames)
        base = model.end_logits(features)
        start, k = 2, 2  # the output for segment [2, 5) sees o_2 .. o_5
        changed = features.clone()
        changed[start + k + 2 :] = torch.randn_like(changed[start + k + 2 :])
        other = model.end_logits(changed)
    torch.testing.assert_close(other[start, : k + 1], base[start, : k + 1])
    assert not torch.allclose(other[start, k + 1 :], base[start, k + 1 :])


def test_an_end_head_with_lookahead_reads_exactly_that_many_frames_past_the_end() -> None:
    model = tiny_ps_model(max_len=6, end_lookahead=2)
    features = random_features(15)
    with torch.no_grad():
        base = model.end_logits(features)
        start, k = 2, 2  # segment [2, 5): the end head reads o_2 .. o_7
        changed = features.clone()
        changed[start + k + 4 :] = torch.randn_like(changed[start + k + 4 :])
        torch.testing.assert_close(model.end_logits(changed)[start, : k + 1], base[start, : k + 1])
        changed[start + k + 3] = torch.randn(16)  # o_7
        assert not torch.allclose(model.end_logits(changed)[start, k], base[start, k])
        # the label still reads the segment alone
        torch.testing.assert_close(model.label_logits(changed, 2, 5), model.label_logits(features, 2, 5))


def test_end_lookahead_is_checked_and_old_checkpoints_read_none() -> None:
    with pytest.raises(ValueError, match="end_lookahead must be in 0..8, got 9"):
        tiny_model_config(end_lookahead=9)
    raw = tiny_model_config(end_lookahead=1).to_json()
    assert ModelConfig.from_json(raw, FEATURES).end_lookahead == 1
    del raw["end_lookahead"]
    assert ModelConfig.from_json(raw, FEATURES).end_lookahead == 0


def test_frames_before_the_start_change_nothing() -> None:
    model = tiny_ps_model(max_len=6)
    features = random_features(15)
    with torch.no_grad():
        base = model.end_logits(features)
        changed = features.clone()
        changed[:5] = torch.randn(5, 16)
        other = model.end_logits(changed)
        label = model.label_logits(features, 5, 9)
        label_other = model.label_logits(changed, 5, 9)
    torch.testing.assert_close(other[5:], base[5:])
    assert not torch.allclose(other[:5], base[:5])
    torch.testing.assert_close(label, label_other)


def test_encoder_has_no_temporal_mixing() -> None:
    model = tiny_ps_model()
    frames = synthetic_episode(4).images[CAMERA]
    with torch.no_grad():
        together = encode_frames(model, frames)
        one_by_one = torch.cat([encode_frames(model, frames[t : t + 1]) for t in range(len(frames))])
    torch.testing.assert_close(together, one_by_one, rtol=1e-5, atol=1e-5)


def test_label_logits_validate_segment_length() -> None:
    model = tiny_ps_model(max_len=4)
    features = random_features(10)
    assert model.label_logits(features, 2, 6).shape == (NUM_CLASSES,)
    with pytest.raises(ValueError, match="1..4 steps"):
        model.label_logits(features, 2, 7)


def test_previous_actions_shift_by_one_and_name_the_bad_entry() -> None:
    encoder = tiny_ps_model(num_actions=3).encoders.encoders[1]
    rows = encoder.previous_action_rows(np.array([[2.0], [0.0], [1.0]]), "ep7 actions")
    np.testing.assert_array_equal(rows, [3, 2, 0, 1])
    assert encoder.previous_action_rows(np.zeros((0, 1)), "x").tolist() == [3]  # a lone observation
    with pytest.raises(ValueError, match=r"ep7 actions\[1\] = 1.5: not a discrete action index in 0..2"):
        check_discrete_actions(np.array([[0.0], [1.5]]), 3, "ep7 actions")
    with pytest.raises(ValueError, match=r"ep7 actions\[0\] = 3.0"):
        encoder.previous_action_rows(np.array([[3.0]]), "ep7 actions")
    with pytest.raises(ValueError, match=r"need shape \(T, 1\)"):
        check_discrete_actions(np.zeros((4, 2)), 3, "ep7 actions")


def _inputs(frames: np.ndarray, previous: list[int]) -> dict[str, torch.Tensor]:
    return {CAMERA: torch.from_numpy(frames), ACTION: torch.tensor(previous)}


def test_an_action_model_reads_the_action_that_led_to_each_frame() -> None:
    model = tiny_ps_model(num_actions=3)
    frames = synthetic_episode(2).images[CAMERA][:8]
    actions = [3, 0, 1, 2, 0, 1, 2, 0]
    with torch.no_grad():
        base = model.end_logits(model.encode_steps(_inputs(frames, actions)))
        changed_actions = list(actions)
        changed_actions[4] = 2  # a_3, the action that led to o_4: windows holding o_4 change
        other = model.end_logits(model.encode_steps(_inputs(frames, changed_actions)))
        assert model.encode_steps(_inputs(frames, actions)).shape == (8, 16 + 4)
    torch.testing.assert_close(other[1, :2], base[1, :2])  # [1, 2) and [1, 3) end before o_4
    assert not torch.allclose(other[1, 2], base[1, 2])  # [1, 4) ends at o_4
    with pytest.raises(KeyError):
        model.encode_steps({CAMERA: torch.from_numpy(frames)})


def test_episode_inputs_follow_the_features_the_model_reads() -> None:
    model = tiny_ps_model(num_actions=3)
    episode = synthetic_episode(2)
    inputs = model.encoders.episode_inputs(episode)
    assert set(inputs) == {CAMERA, ACTION}
    np.testing.assert_array_equal(inputs[ACTION][1:], episode.actions[:, 0])
    assert inputs[ACTION][0] == 3  # o_0: no action led to it
    with torch.no_grad():
        torch.testing.assert_close(model.encode_episode(episode), model.encode_steps(as_tensors(inputs)))
    no_camera = Episode("blind", episode.actions, {}, segments=[])
    with pytest.raises(FeatureError, match=f"episode 'blind'.*{CAMERA}"):
        model.encode_episode(no_camera)


def test_checkpoint_of_an_action_model_round_trips(tmp_path) -> None:
    model = tiny_ps_model(seed=2, num_actions=3, end_lookahead=1)
    save_model(tmp_path / "ps.pt", model)
    loaded, _ = load_model(tmp_path / "ps.pt")
    assert loaded.reads_actions and loaded.cfg.features.action.num_values == 3
    assert loaded.lookahead == 1
    assert [spec.kind for spec in loaded.cfg.encoders] == ["babyai.grid_tiles", "discrete_action"]
    frames, actions = synthetic_episode(1).images[CAMERA][:6], [3, 0, 1, 2, 0, 1]
    with torch.no_grad():
        torch.testing.assert_close(
            loaded.end_logits(loaded.encode_steps(_inputs(frames, actions))),
            model.end_logits(model.encode_steps(_inputs(frames, actions))),
        )


def test_checkpoint_round_trip_gives_identical_outputs(tmp_path) -> None:
    model = tiny_ps_model(seed=5)
    path = tmp_path / "ps.pt"
    save_model(path, model, meta={"note": "test"})
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == "playseg-checkpoint" and raw["kind"] == "ps"
    assert raw["config"]["instructions"] == INSTRUCTIONS and raw["config"]["trunk"]["max_len"] == 6
    assert sorted(raw["features"]["features"]) == [ACTION, CAMERA] and "features" not in raw["config"]
    loaded, meta = load_model(path)
    assert isinstance(loaded, PSModel) and loaded.instructions == INSTRUCTIONS
    assert meta == {"note": "test"}
    episode = synthetic_episode(1)
    with torch.no_grad():
        torch.testing.assert_close(
            loaded.end_logits(loaded.encode_episode(episode)), model.end_logits(model.encode_episode(episode))
        )


def test_labeller_checkpoint_round_trip(tmp_path) -> None:
    torch.manual_seed(0)
    model = LabelModel(tiny_model_config(num_layers=1), INSTRUCTIONS).eval()
    save_model(tmp_path / "lab.pt", model)
    loaded, _ = load_model(tmp_path / "lab.pt")
    features = random_features(8)
    assert isinstance(loaded, LabelModel)
    torch.testing.assert_close(loaded.label_logits(features, 1, 5), model.label_logits(features, 1, 5))
    with pytest.raises(CheckpointError, match="lab.pt.*a 'labeller' checkpoint, expected ps"):
        load_model(tmp_path / "lab.pt", kinds=("ps",))


def test_a_checkpoint_refuses_data_with_other_features(tmp_path) -> None:
    model = tiny_ps_model(num_actions=3)
    save_model(tmp_path / "ps.pt", model)
    loaded, _ = load_model(tmp_path / "ps.pt")
    loaded.cfg.check_features(FEATURES, "model ps.pt")  # the same features: accepted
    other_camera = Features.of(
        [Feature("observation.images.wrist", "image", "uint8", (64, 64, 3)), FEATURES.action]
    )
    with pytest.raises(FeatureError, match=f"model ps.pt reads feature '{CAMERA}', which the data lacks"):
        loaded.cfg.check_features(other_camera, "model ps.pt")
    bigger = Features.of([Feature(CAMERA, "image", "uint8", (96, 96, 3)), FEATURES.action])
    with pytest.raises(FeatureError, match=CAMERA):
        loaded.cfg.check_features(bigger, "model ps.pt")
    five = FEATURES.with_action(Feature(ACTION, "action", "float32", (1,), num_values=5))
    with pytest.raises(FeatureError, match="action.*discrete, 3 values.*discrete, 5 values"):
        loaded.cfg.check_features(five, "model ps.pt")
    planar = FEATURES.with_action(Feature(ACTION, "action", "float32", (2,)))
    with pytest.raises(FeatureError, match="action.*discrete, 3 values.*continuous, 2-d"):
        loaded.cfg.check_features(planar, "model ps.pt")
    # An undeclared one-value action (a source without a schema) is read as indices, each one checked.
    loaded.cfg.check_features(FEATURES.with_action(Feature(ACTION, "action", "float32", (1,))), "model ps.pt")


def test_corrupt_checkpoints_fail_clearly(tmp_path) -> None:
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a checkpoint")
    with pytest.raises(ValueError, match="garbage.pt"):
        load_model(garbage)

    unsafe = tmp_path / "unsafe.pt"
    torch.save({"kind": "ps", "object": UnsafePayload()}, unsafe)
    with pytest.raises(ValueError, match="unsafe.pt.*cannot be read safely"):
        load_model(unsafe)

    untagged = tmp_path / "untagged.pt"
    torch.save({"kind": "ps", "config": {}, "state_dict": {}}, untagged)  # the format before this one
    with pytest.raises(ValueError, match="untagged.pt.*not a playseg-checkpoint file"):
        load_model(untagged)

    model = tiny_ps_model()
    wrong_shape = tmp_path / "wrong.pt"
    save_model(wrong_shape, model)
    payload = torch.load(wrong_shape, weights_only=True)
    payload["config"]["trunk"]["hidden_dim"] = 32
    torch.save(payload, wrong_shape)
    with pytest.raises(ValueError, match="wrong.pt.*not a valid ps model"):
        load_model(wrong_shape)

    with pytest.raises(ValueError, match="missing.pt.*no such file"):
        load_model(tmp_path / "missing.pt")


def test_encoder_ignores_where_things_are() -> None:
    """No position-specific path: moving the whole scene by one tile leaves the features unchanged."""
    model = tiny_ps_model(seed=2)
    rng = np.random.default_rng(0)
    frame = np.zeros((64, 64, 3), np.uint8)
    frame[16:40, 16:40] = rng.integers(0, 256, size=(24, 24, 3), dtype=np.uint8)  # away from the border
    shifted = np.roll(frame, shift=(8, -8), axis=(0, 1))
    other = frame.copy()
    other[24:32, 24:32] = 255 - other[24:32, 24:32]  # a different tile content: features must change
    with torch.no_grad():
        features = encode_frames(model, np.stack([frame, shifted, other]))
    torch.testing.assert_close(features[1], features[0], rtol=1e-4, atol=1e-5)
    assert not torch.allclose(features[2], features[0], atol=1e-4)
