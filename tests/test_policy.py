"""The BabyAI policy: checkpoints, egocentric view, seeded training, reproducible evaluation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX

from playseg_core.checkpoint import CheckpointError
from playseg_core.domains.babyai.evaluation import RandomPolicy, bot_demonstrations, evaluate_policy
from playseg_core.domains.babyai.imitation import (
    PolicyTrainConfig,
    learning_rate_at,
    mirror_samples,
    train_policy,
)
from playseg_core.domains.babyai.policy import (
    WORD_TO_ID,
    PolicyConfig,
    PolicyNet,
    egocentric_offsets,
    encode_instructions,
    load_policy,
    save_policy,
    to_egocentric,
    tokenize,
)

pytestmark = pytest.mark.slow  # most tests read a policy trained once for the module

SMALL = PolicyConfig(channels=16, cell_embedding=16, word_embedding=16, instruction_dim=32, head_hidden=32)


@pytest.fixture(scope="module")
def demonstrations():
    return bot_demonstrations(800, seed=10_000)


@pytest.fixture(scope="module")
def trained(demonstrations):
    config = PolicyTrainConfig(steps=300, batch_size=128, learning_rate=3e-3, seed=0, policy=SMALL)
    return train_policy(demonstrations, config, progress=False)


def test_tokenizer_maps_unknown_words_to_one_id():
    assert tokenize("Go to the RED ball") == [WORD_TO_ID[w] for w in ("go", "to", "the", "red", "ball")]
    assert tokenize("go to the magenta ball")[3] == WORD_TO_ID["<unk>"]
    ids, lengths = encode_instructions(["go to a key", "go to the red ball"])
    assert ids.shape == (2, 5) and lengths.tolist() == [4, 5] and ids[0, 4] == 0


def test_bot_demonstrations_are_consistent(demonstrations):
    assert len(demonstrations) == 800  # the bot solves every GoToLocal episode
    for instruction, states, actions in demonstrations[:50]:
        assert instruction.startswith("go to ")
        assert states.shape == (len(actions) + 1, 8, 8, 3) and states.dtype == np.uint8
        assert (states[:, :, :, 0] == 10).sum(axis=(1, 2)).tolist() == [1] * len(states)
        assert set(actions.tolist()) <= {0, 1, 2}


def agent_position(state: np.ndarray) -> tuple[np.ndarray, int]:
    x, y = np.argwhere(state[:, :, 0] == 10)[0]
    return np.array([x, y]), int(state[x, y, 2])


def test_egocentric_view_puts_what_is_ahead_above_the_agent(demonstrations):
    offsets = egocentric_offsets(11)
    for _, states, _ in demonstrations[:30]:
        view = to_egocentric(torch.from_numpy(states).long(), offsets).numpy()
        for state, ego in zip(states, view, strict=True):
            position, direction = agent_position(state)
            step = np.array([(1, 0), (0, 1), (-1, 0), (0, -1)][direction])
            assert ego[5, 5, 0] == 10  # the agent is at the centre
            assert (ego[4, 5] == state[tuple(position + step)]).all()  # the cell in front is one row up
            right = np.array([-step[1], step[0]])
            assert (ego[5, 6] == state[tuple(position + right)]).all()  # its right is one column right


def test_mirrored_demonstrations_obey_the_dynamics(demonstrations):
    # After a mirrored "forward", the agent must move one cell along its mirrored direction.
    for _, states, actions in demonstrations[:30]:
        mirrored, mirrored_actions = mirror_samples(torch.from_numpy(states), torch.from_numpy(actions))
        mirrored = mirrored.numpy()
        assert ((actions == 0) == (mirrored_actions.numpy() == 1)).all()
        for t, action in enumerate(mirrored_actions.tolist()):
            before, direction = agent_position(mirrored[t])
            after, new_direction = agent_position(mirrored[t + 1])
            if action == 2:
                step = [(1, 0), (0, 1), (-1, 0), (0, -1)][direction]
                assert (after - before).tolist() == list(step)
            elif action in (0, 1):
                assert new_direction == (direction + (1 if action == 1 else -1)) % 4


def test_learning_rate_warms_up_then_decays_to_its_floor():
    config = PolicyTrainConfig(steps=1000, learning_rate=1e-3, warmup_steps=100, min_learning_rate=1e-5)
    rates = [learning_rate_at(step, config) for step in range(1, 1001)]
    assert rates[0] == pytest.approx(1e-5) and rates[99] == pytest.approx(1e-3)  # linear warm-up
    assert all(a >= b for a, b in zip(rates[99:], rates[100:], strict=False))  # then never rises
    assert rates[549] == pytest.approx((1e-3 + 1e-5) / 2, rel=0.01)  # half-way down the cosine
    assert rates[-1] == pytest.approx(1e-5)
    short = PolicyTrainConfig(steps=16, warmup_steps=50, learning_rate=1e-3, min_learning_rate=1e-5)
    assert learning_rate_at(2, short) == pytest.approx(1e-3)  # warm-up cut to an eighth of the run
    assert learning_rate_at(16, short) == pytest.approx(1e-5)  # and it still decays
    constant = PolicyTrainConfig(steps=10, warmup_steps=0, learning_rate=2e-3, min_learning_rate=2e-3)
    assert {learning_rate_at(step, constant) for step in range(1, 11)} == {2e-3}


def test_training_is_seeded(demonstrations):
    config = PolicyTrainConfig(steps=5, batch_size=32, seed=3, policy=SMALL)
    first, _ = train_policy(demonstrations[:50], config, progress=False)
    second, _ = train_policy(demonstrations[:50], config, progress=False)
    other, _ = train_policy(
        demonstrations[:50], PolicyTrainConfig(steps=5, batch_size=32, seed=4, policy=SMALL), progress=False
    )
    for name, tensor in first.state_dict().items():
        assert torch.equal(tensor, second.state_dict()[name]), name
    assert not torch.equal(first.head[-1].weight, other.head[-1].weight)


def test_checkpoint_round_trip(tmp_path: Path, trained, demonstrations):
    model, stats = trained
    path = tmp_path / "policy.pt"
    save_policy(path, model, {"num_segments": stats.num_segments, "note": "test"})
    loaded, meta = load_policy(path)
    assert loaded.config == SMALL and meta == {"num_segments": 800, "note": "test"}
    states = np.stack([s[0] for _, s, _ in demonstrations[:64]])
    ids, lengths = encode_instructions([i for i, _, _ in demonstrations[:64]])
    with torch.no_grad():
        expected = model.eval()(torch.from_numpy(states), ids, lengths)
        assert torch.equal(loaded(torch.from_numpy(states), ids, lengths), expected)


def test_bad_checkpoints_name_the_file(tmp_path: Path, trained):
    model, _ = trained
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a checkpoint")
    with pytest.raises(CheckpointError, match="garbage.pt"):
        load_policy(garbage)

    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": model.state_dict()}, foreign)
    with pytest.raises(CheckpointError, match="foreign.pt: not a playseg-checkpoint file"):
        load_policy(foreign)

    good = tmp_path / "good.pt"
    save_policy(good, model, {})
    checkpoint = torch.load(good, weights_only=True)
    checkpoint["config"]["channels"] = 24  # weights no longer fit the config
    wrong_shapes = tmp_path / "wrong_shapes.pt"
    torch.save(checkpoint, wrong_shapes)
    with pytest.raises(CheckpointError, match="wrong_shapes.pt.*do not match"):
        load_policy(wrong_shapes)

    checkpoint = torch.load(good, weights_only=True)
    del checkpoint["state_dict"]["head.1.weight"]
    missing = tmp_path / "missing_key.pt"
    torch.save(checkpoint, missing)
    with pytest.raises(CheckpointError, match="(?s)missing_key.pt.*head.1.weight"):
        load_policy(missing)


def test_checkpoint_written_before_relevance_maps_loads_as_film_only(tmp_path: Path, demonstrations):
    film_only = PolicyConfig(**{**SMALL.__dict__, "relevance_maps": 0})
    model, _ = train_policy(
        demonstrations[:50], PolicyTrainConfig(steps=3, batch_size=16, policy=film_only), progress=False
    )
    assert model.relevance_queries is None
    path = tmp_path / "old.pt"
    save_policy(path, model, {})
    checkpoint = torch.load(path, weights_only=True)
    del checkpoint["config"]["relevance_maps"]  # as a checkpoint from before the field existed
    torch.save(checkpoint, path)
    loaded, _ = load_policy(path)
    assert loaded.config.relevance_maps == 0
    states = torch.from_numpy(np.stack([s[0] for _, s, _ in demonstrations[:8]]))
    ids, lengths = encode_instructions([i for i, _, _ in demonstrations[:8]])
    with torch.no_grad():
        assert torch.equal(loaded(states, ids, lengths), model.eval()(states, ids, lengths))


def test_a_trained_policys_relevance_maps_find_the_instructed_object(trained):
    """Among the objects in view, the cell a relevance map scores highest is the instructed one far more
    often than chance: the maps ground the instruction (policy.py)."""
    model, _ = trained
    episodes = bot_demonstrations(200, seed=20_000)  # not the training episodes
    states = torch.from_numpy(np.stack([states[0] for _, states, _ in episodes]))
    ids, lengths = encode_instructions([instruction for instruction, _, _ in episodes])
    with torch.no_grad():
        cells = model.embed_cells(states)
        maps = model.relevance(cells, model.instruction_encoder(ids, lengths))  # (B, V, V, K)
        view = to_egocentric(states.long(), model.view_offsets)
    hits, chance = np.zeros(maps.shape[-1]), 0.0
    pickable_types = torch.tensor([OBJECT_TO_IDX[kind] for kind in ("key", "ball", "box")])
    for index, (instruction, _, _) in enumerate(episodes):
        colour, kind = instruction.split()[-2:]
        objects = torch.isin(view[index, ..., 0], pickable_types)
        goal = objects & (view[index, ..., 0] == OBJECT_TO_IDX[kind])
        goal &= view[index, ..., 1] == COLOR_TO_IDX[colour]
        assert goal.any()  # the whole room is in view
        chance += goal.sum().item() / objects.sum().item()
        for k in range(maps.shape[-1]):
            best = maps[index, ..., k].masked_fill(~objects, float("-inf")).argmax()
            hits[k] += bool(goal.flatten()[best])
    hits, chance = hits / len(episodes), chance / len(episodes)
    print(f"instructed object found: per map {np.round(hits, 3).tolist()}, chance {chance:.3f}")
    assert hits.max() >= 0.8 and hits.max() >= chance + 0.4


def test_evaluation_is_reproducible(trained):
    model, _ = trained
    first = evaluate_policy(model, num_episodes=32, seed=7, num_envs=16)
    second = evaluate_policy(model, num_episodes=32, seed=7, num_envs=16)
    assert first.episode_success == second.episode_success
    assert first.episode_steps == second.episode_steps
    assert first.success_rate == sum(first.episode_success) / 32


def test_trained_policy_beats_untrained_and_random(trained):
    model, stats = trained
    assert stats.final_loss < stats.losses[0][1]
    torch.manual_seed(0)
    untrained = PolicyNet(SMALL).eval()
    trained_score = evaluate_policy(model, num_episodes=64, seed=0).success_rate
    untrained_score = evaluate_policy(untrained, num_episodes=64, seed=0).success_rate
    random_score = evaluate_policy(RandomPolicy(0), num_episodes=64, seed=0).success_rate
    print(f"success: trained {trained_score:.3f} untrained {untrained_score:.3f} random {random_score:.3f}")
    assert trained_score >= untrained_score + 0.2
    assert trained_score >= random_score + 0.1


def test_evaluation_counts_its_own_steps_past_the_levels_default_limit():
    """The level's own limit (64 steps in an 8x8 room) is off: success within max_steps is what counts."""
    result = evaluate_policy(RandomPolicy(1), num_episodes=100, max_steps=100, seed=5, num_envs=50)
    late = [s for s, ok in zip(result.episode_steps, result.episode_success, strict=True) if ok and s > 64]
    assert late, "no episode succeeded after step 64: the env's step limit cut the episodes short"
    assert all(s <= 100 for s in result.episode_steps)


def test_learner_settings_choose_the_network():
    from playseg_core.augment.policies import load_policy_learner

    learner = load_policy_learner("babyai.film", {"channels": 24, "relevance_maps": 0, "steps": 7})
    network = learner.train_config.policy
    assert (network.channels, network.relevance_maps, learner.train_config.steps) == (24, 0, 7)
    assert load_policy_learner("babyai.film", {}).train_config.policy.relevance_maps == 4
    with pytest.raises(ValueError, match="relevance_maps >= 0"):
        load_policy_learner("babyai.film", {"relevance_maps": -1})
    with pytest.raises(ValueError, match="unknown settings"):
        load_policy_learner("babyai.film", {"relevance": 2})
