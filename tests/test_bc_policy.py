"""The generic behaviour-cloning policy (playseg_core/augment/bc_policy.py) on synthetic robot-shaped clips."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from playseg_core.augment.bc_policy import (
    BCPolicyLearner,
    InstructionAttention,
    load_bc_policy,
    save_bc_policy,
)
from playseg_core.augment.policies import load_policy_learner
from playseg_core.augment.retraining import AugmentationTrainer, TrainerConfig
from playseg_core.checkpoint import CheckpointError, read_checkpoint
from playseg_core.data.episode import Segment, SegmentClip
from playseg_core.data.features import ACTION, STATE, Feature, FeatureError, Features
from playseg_core.ps.encoders import cell_entities

CAMERA = "observation.images.wrist"
INSTRUCTIONS = ("push the block left", "push the block right", "hold the gripper still")
FAST = {"steps": 300, "batch_size": 64, "val_fraction": 0.1, "seed": 0}


def robot_features(discrete: bool = False) -> Features:
    action = (
        Feature(ACTION, "action", "float32", (1,), num_values=6)
        if discrete
        else Feature(ACTION, "action", "float32", (7,))
    )
    return Features.of(
        [Feature(CAMERA, "image", "uint8", (16, 16, 3)), Feature(STATE, "state", "float32", (7,)), action],
        fps=10.0,
    )


def rule(states: np.ndarray, k: int, discrete: bool) -> np.ndarray:
    """The expert: continuous, a fixed per-instruction linear map of the state; discrete, which of the
    first three state values is largest, shifted by 3 for the second half of the instructions."""
    if discrete:
        return (np.argmax(states[:, :3], axis=1) + 3 * (k % 2)).astype(np.float32)[:, None]
    signs = np.array([1.0, -1.0, 0.0])[k]
    offsets = np.linspace(-1.0, 1.0, 7) * (k - 1)
    return (signs * states + offsets).astype(np.float32)


def make_clips(num: int, seed: int, discrete: bool = False, length: int = 8) -> list[SegmentClip]:
    rng = np.random.default_rng(seed)
    clips = []
    for i in range(num):
        k = i % len(INSTRUCTIONS)
        states = rng.normal(size=(length + 1, 7)).astype(np.float32)
        frames = rng.integers(0, 256, size=(length + 1, 16, 16, 3), dtype=np.uint8)
        clips.append(
            SegmentClip(
                episode_id=f"ep{i}",
                segment=Segment(0, length, INSTRUCTIONS[k]),
                actions=rule(states[:length], k, discrete),
                images={CAMERA: frames},
                state=states,
                source="annotation",
            )
        )
    return clips


@pytest.fixture(scope="module")
def trained() -> tuple[BCPolicyLearner, object, object]:
    learner = load_policy_learner("bc", FAST, features=robot_features())
    policy, report = learner.train(make_clips(60, seed=1))
    return learner, policy, report


def test_generic_names_resolve_and_unknown_ones_are_named() -> None:
    learner = load_policy_learner("bc", {"channels": 32, "eval_max_steps": 5}, features=robot_features())
    assert isinstance(learner, BCPolicyLearner) and learner.settings.hidden == 32
    assert sorted(learner.features.by_name) == sorted([CAMERA, STATE, ACTION])
    with pytest.raises(ValueError, match="'nope': not a generic policy"):
        load_policy_learner("nope")
    with pytest.raises(ValueError, match=r"unknown settings \['bogus'\]"):
        load_policy_learner("bc", {"bogus": 1}, features=robot_features())
    with pytest.raises(FeatureError, match="needs the data's declared features"):
        load_policy_learner("bc", {})


@pytest.mark.slow
def test_training_beats_the_mean_action_on_held_out_clips(trained) -> None:
    _, _, report = trained
    assert report.num_segments == 60 and report.num_val_segments == 6
    assert report.val_accuracy is None
    assert math.isfinite(report.val_loss) and report.baseline_val_loss > 0.5
    assert report.val_loss < 0.3 * report.baseline_val_loss, report
    assert report.losses[-1][1] < report.losses[0][1]


@pytest.mark.slow  # the module's trained policy
def test_act_is_batched_and_checkpoints_round_trip(trained, tmp_path: Path) -> None:
    learner, policy, _ = trained
    clip = make_clips(1, seed=9, length=5)[0]
    observations = {CAMERA: clip.images[CAMERA], STATE: clip.state}
    instructions = [
        INSTRUCTIONS[0],
        INSTRUCTIONS[1],
        "push the block up",
        "",
        INSTRUCTIONS[2],
        INSTRUCTIONS[0],
    ]
    actions = policy.act(observations, instructions)
    assert actions.shape == (6, 7) and actions.dtype == np.float32
    learner.save(tmp_path / "p.pt", policy, {"version": 2})
    loaded, meta = learner.load(tmp_path / "p.pt")
    assert meta == {"version": 2}
    np.testing.assert_array_equal(loaded.act(observations, instructions), actions)
    checkpoint = read_checkpoint(tmp_path / "p.pt", kinds=("policy",))
    assert checkpoint.config["policy"] == "bc"
    checkpoint.check_features(robot_features())
    other = robot_features().with_camera(Feature(CAMERA, "image", "uint8", (32, 32, 3)))
    with pytest.raises(FeatureError, match=f"p.pt reads {CAMERA}: image \\[16, 16, 3\\]"):
        checkpoint.check_features(other)
    with pytest.raises(FeatureError, match="action"):
        checkpoint.check_features(robot_features(discrete=True))
    with pytest.raises(FeatureError, match=f"{CAMERA!r} must be \\[6, 16, 16, 3\\]"):
        policy.act({CAMERA: observations[CAMERA][:, :8], STATE: clip.state}, instructions)


@pytest.mark.slow  # the module's trained policy
def test_a_foreign_policy_checkpoint_is_refused(trained, tmp_path: Path) -> None:
    _, policy, _ = trained
    policy.config = {**policy.config, "policy": "other"}
    try:
        load_policy_learner("bc", {}, features=robot_features()).save(tmp_path / "p.pt", policy, {})
    finally:
        policy.config = {**policy.config, "policy": "bc"}
    with pytest.raises(CheckpointError, match="a 'other' policy, expected 'bc'"):
        load_bc_policy(tmp_path / "p.pt")


@pytest.mark.slow
def test_discrete_actions_reach_high_validation_accuracy() -> None:
    learner = load_policy_learner("bc", FAST, features=robot_features(discrete=True))
    policy, report = learner.train(make_clips(60, seed=2, discrete=True))
    assert report.val_accuracy > 0.9 and report.val_loss < 0.5 * report.baseline_val_loss, report
    clip = make_clips(2, seed=5, discrete=True, length=3)[1]
    actions = policy.act({CAMERA: clip.images[CAMERA], STATE: clip.state}, [clip.segment.instruction] * 4)
    assert actions.shape == (4,) and actions.dtype == np.int64
    np.testing.assert_array_equal(actions, rule(clip.state, 1, True)[:, 0])


def test_no_simulator_so_no_evaluation_and_the_trainer_retrains(tmp_path: Path) -> None:
    learner = load_policy_learner("bc", {**FAST, "steps": 20}, features=robot_features())
    clips = make_clips(12, seed=3)
    trainer = AugmentationTrainer(
        TrainerConfig(str(tmp_path / "buf"), str(tmp_path / "ckpt")), learner, clips[:8]
    )
    for clip in clips[8:]:
        trainer.add(clip)
    version = trainer.retrain()
    assert version.version == 1 and math.isnan(version.success_rate) and version.eval_episodes == 0
    assert trainer.evaluate() is None
    assert learner.evaluate(learner.load(Path(version.checkpoint))[0], 4, 0) is None
    trainer.close()


def bimodal_clips(num: int, seed: int) -> list[SegmentClip]:
    """Pairs of clips with the same observations and instruction whose expert moves along the first
    action axis +1 in one and -1 in the other, never in between; the other axes follow `rule`."""
    clips = []
    for clip in make_clips(num // 2, seed):
        for sign in (1.0, -1.0):
            actions = clip.actions.copy()
            actions[:, 0] = sign
            clips.append(replace(clip, actions=actions))
    return clips


@pytest.mark.slow
def test_a_bins_head_acts_like_one_of_the_demonstrators_and_regression_averages_them(
    tmp_path: Path,
) -> None:
    clips = bimodal_clips(60, seed=4)
    probe = make_clips(1, seed=8, length=16)[0]
    observations = {CAMERA: probe.images[CAMERA], STATE: probe.state}
    instructions = [INSTRUCTIONS[0]] * 17
    first_axis = {}
    for head in ("regress", "bins"):
        learner = load_policy_learner("bc", {**FAST, "action_head": head}, features=robot_features())
        policy, report = learner.train(clips)
        assert report.val_loss < 0.5 * report.baseline_val_loss, (head, report)
        actions = policy.act(observations, instructions)
        first_axis[head] = actions[:, 0]
        if head == "bins":
            assert report.val_accuracy > 0.5, report
            learner.save(tmp_path / "b.pt", policy, {})
            loaded, _ = learner.load(tmp_path / "b.pt")
            np.testing.assert_array_equal(loaded.act(observations, instructions), actions)
    # The regression lands between the two ways (mean |a| well under 1); the bins take one of them.
    assert np.abs(first_axis["regress"]).mean() < 0.5, first_axis
    assert np.abs(first_axis["bins"]).mean() > 0.9, first_axis


def test_bins_span_the_declared_bounds_and_acting_stays_inside_them() -> None:
    features = robot_features()
    bounded = features.with_action(
        Feature(ACTION, "action", "float32", (7,), low=(-0.5,) * 7, high=(0.5,) * 7)
    )
    learner = load_policy_learner("bc", {**FAST, "steps": 5, "action_head": "bins"}, features=bounded)
    clips = make_clips(6, seed=1)
    policy = learner.build(clips)
    assert policy.config["action_low"] == [-0.5] * 7 and policy.config["action_high"] == [0.5] * 7
    unbounded = load_policy_learner("bc", {"action_head": "bins"}, features=features).build(clips)
    seen = np.concatenate([c.actions for c in clips])
    np.testing.assert_allclose(unbounded.config["action_low"], seen.min(0), rtol=1e-6)
    centres = policy.bin_centres(torch.arange(21)[:, None].expand(21, 7))
    np.testing.assert_allclose(centres[[0, 10, 20], 0].numpy(), [-0.5, 0.0, 0.5], atol=1e-6)
    np.testing.assert_array_equal(policy.action_bin(centres).numpy(), np.arange(21)[:, None].repeat(7, 1))
    clip = clips[0]
    actions = policy.act({CAMERA: clip.images[CAMERA], STATE: clip.state}, [INSTRUCTIONS[0]] * 9)
    # Every value is a bin centre: -0.5, -0.45, ..., 0.5.
    np.testing.assert_allclose(actions * 20, np.round(actions * 20), atol=1e-4)
    assert actions.min() >= -0.5 and actions.max() <= 0.5


def test_bad_action_head_settings_fail_in_one_line() -> None:
    with pytest.raises(ValueError, match="action_head must be 'regress' or 'bins'.*'flow'"):
        load_policy_learner("bc", {"action_head": "flow"}, features=robot_features())
    with pytest.raises(ValueError, match="got 'bins' and 1"):
        load_policy_learner("bc", {"action_head": "bins", "action_bins": 1}, features=robot_features())
    with pytest.raises(ValueError, match="'bins' needs a continuous action; 'action' is discrete"):
        load_policy_learner("bc", {"action_head": "bins"}, features=robot_features(discrete=True))


@pytest.mark.slow
def test_an_instruction_film_head_learns_and_its_flag_reads_from_text(tmp_path: Path) -> None:
    settings = {**FAST, "instruction_film": "true"}
    learner = load_policy_learner("bc", settings, features=robot_features())
    assert learner.settings.instruction_film is True
    assert (
        load_policy_learner(
            "bc", {"instruction_film": "False"}, features=robot_features()
        ).settings.instruction_film
        is False
    )
    policy, report = learner.train(make_clips(60, seed=1))
    assert policy.film is not None and report.val_loss < 0.3 * report.baseline_val_loss, report
    learner.save(tmp_path / "f.pt", policy, {})
    loaded, _ = learner.load(tmp_path / "f.pt")
    clip = make_clips(1, seed=9, length=4)[0]
    observations = {CAMERA: clip.images[CAMERA], STATE: clip.state}
    np.testing.assert_array_equal(
        loaded.act(observations, list(INSTRUCTIONS[:2]) * 2 + [""]),
        policy.act(observations, list(INSTRUCTIONS[:2]) * 2 + [""]),
    )
    with pytest.raises(ValueError, match="instruction_film must be true or false, got 'maybe'"):
        load_policy_learner("bc", {"instruction_film": "maybe"}, features=robot_features())


def test_attention_positions_are_where_the_matching_cell_is() -> None:
    attention = InstructionAttention(instruction_dim=3, entity_dim=4, queries=2)
    with torch.no_grad():  # query 0 looks for channel 0, query 1 for channel 1, sharply
        attention.query.weight.zero_()
        attention.query.bias.zero_()
        attention.query.weight[0, 0] = 50.0
        attention.query.weight[4 + 1, 0] = 50.0
    cells = torch.zeros(1, 4, 3, 5)  # 3 rows, 5 columns
    cells[0, 0, 2, 4] = 1.0  # bottom row, last column
    cells[0, 1, 0, 1] = 1.0  # top row, second column
    out = attention(*cell_entities(cells), torch.tensor([[1.0, 0.0, 0.0]]))
    assert out.shape == (1, attention.out_dim) and attention.out_dim == 2 * (2 + 4)
    where = out.view(2, 6)[:, :2]
    torch.testing.assert_close(where, torch.tensor([[1.0, 1.0], [-0.5, -1.0]]), atol=0.02, rtol=0)
    torch.testing.assert_close(out.view(2, 6)[:, 2:4], torch.eye(2), atol=0.02, rtol=0)


def square_clips(num: int, seed: int) -> list[SegmentClip]:
    """A red and a blue square anywhere in a 32x32 frame; the action is the named square's centre."""
    rng = np.random.default_rng(seed)
    colours = {"reach the red square": (255, 0, 0), "reach the blue square": (0, 0, 255)}
    clips = []
    for i in range(num):
        frames = np.zeros((5, 32, 32, 3), np.uint8)
        actions = np.zeros((4, 2), np.float32)
        names = list(colours)
        named = names[i % 2]
        for t in range(5):
            corners = rng.integers(0, 26, size=(2, 2))
            for name, (row, column) in zip(names, corners, strict=True):
                frames[t, row : row + 6, column : column + 6] = colours[name]
                if name == named and t < 4:
                    actions[t] = [(column + 3) / 16 - 1, (row + 3) / 16 - 1]
        clips.append(
            SegmentClip(f"ep{i}", Segment(0, 4, named), actions, {CAMERA: frames}, None, "annotation")
        )
    return clips


@pytest.mark.slow
def test_instruction_attention_finds_the_named_object_and_round_trips(tmp_path: Path) -> None:
    features = Features.of(
        [Feature(CAMERA, "image", "uint8", (32, 32, 3)), Feature(ACTION, "action", "float32", (2,))], 10.0
    )
    settings = {**FAST, "steps": 400, "instruction_attention": 2, "instruction_dropout": 0.0}
    learner = load_policy_learner("bc", settings, features=features)
    policy, report = learner.train(square_clips(200, seed=3))
    assert len(policy.attention) == 1
    assert report.val_loss < 0.3 * report.baseline_val_loss, report
    learner.save(tmp_path / "a.pt", policy, {})
    loaded, _ = learner.load(tmp_path / "a.pt")
    clip = square_clips(2, seed=9)[1]
    observations = {CAMERA: clip.images[CAMERA]}
    instructions = ["reach the red square", "reach the blue square"] * 2 + ["reach the red square"]
    np.testing.assert_array_equal(
        loaded.act(observations, instructions), policy.act(observations, instructions)
    )
    with pytest.raises(ValueError, match="instruction_attention needs a camera encoder that gives entities"):
        state_only = Features.of([robot_features()[STATE], robot_features()[ACTION]], 10.0)
        load_policy_learner("bc", {**FAST, "instruction_attention": 1}, features=state_only).train(
            make_clips(6, seed=1)
        )
    with pytest.raises(ValueError, match="instruction_attention must be >= 0, got -1"):
        load_policy_learner("bc", {"instruction_attention": -1}, features=features)


@pytest.mark.slow
def test_excluded_state_dimensions_are_not_read() -> None:
    names = tuple(f"joint_{i}" for i in range(7))
    base = robot_features()
    features = Features.of(
        [base[CAMERA], Feature(STATE, "state", "float32", (7,), names=names), base[ACTION]], 10.0
    )
    learner = load_policy_learner("bc", {**FAST, "state_exclude": "joint_0, joint_1"}, features=features)
    clips = make_clips(60, seed=1)
    policy, _ = learner.train(clips)
    clip = clips[0]
    changed = clip.state.copy()
    changed[:, :2] += 5.0
    instructions = [clip.segment.instruction] * len(changed)
    np.testing.assert_array_equal(
        policy.act({CAMERA: clip.images[CAMERA], STATE: changed}, instructions),
        policy.act({CAMERA: clip.images[CAMERA], STATE: clip.state}, instructions),
    )
    changed[:, 2] += 5.0
    assert not np.array_equal(
        policy.act({CAMERA: clip.images[CAMERA], STATE: changed}, instructions),
        policy.act({CAMERA: clip.images[CAMERA], STATE: clip.state}, instructions),
    )
    with pytest.raises(ValueError, match=r"state_exclude names \['elbow'\].*joint_0"):
        load_policy_learner("bc", {"state_exclude": "elbow"}, features=features)
    with pytest.raises(ValueError, match="none declared"):
        load_policy_learner("bc", {"state_exclude": "joint_0"}, features=robot_features())


@pytest.mark.slow
def test_without_known_instructions_only_the_words_count() -> None:
    clips = make_clips(60, seed=1)
    observations = {CAMERA: clips[0].images[CAMERA][:1], STATE: clips[0].state[:1]}
    shuffled = "left block the push"  # the words of INSTRUCTIONS[0] in another order
    for known, same in ((False, True), (True, False)):
        learner = load_policy_learner("bc", {**FAST, "known_instructions": known}, features=robot_features())
        policy, report = learner.train(clips)
        assert report.val_loss < 0.3 * report.baseline_val_loss, report
        assert policy.known.num_embeddings == (len(INSTRUCTIONS) + 1 if known else 1)
        acted = [policy.act(observations, [text]) for text in (INSTRUCTIONS[0], shuffled)]
        assert bool(np.allclose(*acted, atol=1e-5)) is same  # (the mean of the words: any order)


def test_word_order_tells_the_subject_from_the_object(tmp_path: Path) -> None:
    """With ``word_order`` the words are read with their positions and pairs: "push the red block next to
    the blue block" and the same with the colours swapped differ; a bag of words reads them alike. The
    setting survives a checkpoint."""
    from playseg_core.augment.bc_policy import hashed_instruction_words

    one, other = "push the red block next to the blue block", "push the blue block next to the red block"
    assert sorted(hashed_instruction_words(one, 512)) == sorted(hashed_instruction_words(other, 512))
    assert sorted(hashed_instruction_words(one, 4096, True)) != sorted(
        hashed_instruction_words(other, 4096, True)
    )
    clips = make_clips(20, seed=2)
    observations = {CAMERA: clips[0].images[CAMERA][:1], STATE: clips[0].state[:1]}
    for word_order in (False, True):
        settings = {**FAST, "steps": 5, "known_instructions": False, "word_order": word_order}
        policy, _ = load_policy_learner("bc", settings, features=robot_features()).train(clips)
        acted = [policy.act(observations, [text]) for text in (one, other)]
        assert bool(np.allclose(*acted, atol=1e-6)) is not word_order
        save_bc_policy(tmp_path / "p.pt", policy, {})
        loaded, _ = load_bc_policy(tmp_path / "p.pt")
        assert loaded.word_order is word_order
        np.testing.assert_allclose(loaded.act(observations, [other]), acted[1], atol=1e-6)
