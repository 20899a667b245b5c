"""The tabletop's own step encoder (object maps) and the label heads: the maps find each block where the
simulator put it, the domain chooses the scaled blocks and the linear head by default, checkpoints
round-trip, and a text head (on request) labels instruction combinations it never saw in training (a
linear head cannot)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from playseg_core.data.episode import Episode
from playseg_core.data.features import Feature, FeatureError
from playseg_core.domains.tabletop import BLOCK_POSITION_SCALE
from playseg_core.domains.tabletop.encoder import KIND, ObjectMapConfig, ObjectMapEncoder, object_map_spec
from playseg_core.domains.tabletop.play import PlayConfig
from playseg_core.domains.tabletop.render import VIEW_BORDER, Renderer
from playseg_core.domains.tabletop.sim import TabletopSim
from playseg_core.domains.tabletop.spec import BLOCKS, CAMERA, COLOURS, DOMAIN, TABLE_SIZE
from playseg_core.ps.encoders import StepEncoders
from playseg_core.ps.incremental import IncrementalEndScorer
from playseg_core.ps.model import (
    PERIODIC_FREQUENCIES,
    PairDistanceEmbedding,
    PSModel,
    TextLabelHead,
    load_model,
    make_label_head,
    save_model,
)
from playseg_core.ps.training import model_config_for

PARKED = np.array([[0.05 + 0.055 * i, 0.45] for i in range(8)])


def tabletop_shaped_episode(num_steps: int) -> Episode:
    """Random actions and states of the tabletop's shapes, black frames: statistics for a model config."""
    rng = np.random.default_rng(0)
    return Episode(
        "e",
        rng.uniform(-0.2, 0.2, (num_steps, 2)).astype(np.float32),
        {CAMERA: np.zeros((num_steps + 1, 96, 96, 3), np.uint8)},
        rng.uniform(0, 0.5, (num_steps + 1, 4)).astype(np.float32),
    )


def _pixel(point: tuple[float, float], size: int) -> tuple[float, float]:
    """(row, column) of a table point in a ``size`` frame (render.py's projection)."""
    scale = size / (TABLE_SIZE + 2 * VIEW_BORDER)
    return (TABLE_SIZE + VIEW_BORDER - point[1]) * scale - 0.5, (point[0] + VIEW_BORDER) * scale - 0.5


@pytest.mark.parametrize("size", [96, 64])
def test_each_colour_map_is_centred_on_that_colours_blocks(size: int) -> None:
    blocks = PARKED.copy()
    red_cube, blue_cylinder = BLOCKS.index("red cube"), BLOCKS.index("blue cylinder")
    blocks[red_cube], blocks[blue_cylinder] = (0.1, 0.1), (0.4, 0.2)
    sim = TabletopSim()
    sim.place(blocks, (0.25, 0.3))
    frame = Renderer(size).render(sim.scene())
    encoder = ObjectMapEncoder(Feature(CAMERA, "image", "uint8", (size, size, 3)), {})
    masks = encoder.masks(torch.from_numpy(frame)[None])[0].numpy()
    assert masks.max() > 0.99
    rows, columns = np.mgrid[0:size, 0:size]
    # The other blocks are parked along the top edge: the lower half holds one blob of each colour.
    lower = rows > size / 2
    for colour, index in (("red", red_cube), ("blue", blue_cylinder)):
        mask = (masks[COLOURS.index(colour)] > 0.5) * lower
        centre = (float((mask * rows).sum() / mask.sum()), float((mask * columns).sum() / mask.sum()))
        np.testing.assert_allclose(centre, _pixel(tuple(blocks[index]), size), atol=1.0)
    effector = masks[len(COLOURS)] > 0.5
    centre = (
        float((effector * rows).sum() / effector.sum()),
        float((effector * columns).sum() / effector.sum()),
    )
    np.testing.assert_allclose(centre, _pixel((0.25, 0.3), size), atol=1.0)
    # The table and the floor belong to no map.
    table = _pixel((0.25, 0.05), size)
    assert masks[:, round(table[0]), round(table[1])].max() < 0.05
    assert masks[:, size - 1, size - 1].max() < 0.05


def test_a_keypoint_is_where_its_detector_fires(size: int = 96) -> None:
    """With the first convolution made to pass the red map through and the next two to copy it, the
    soft-argmax of keypoint 0 is the red block's image position, in [-1, 1] (x right, y down)."""
    blocks = PARKED.copy()
    red_cube = BLOCKS.index("red cube")
    blocks[BLOCKS.index("red cylinder")] = (0.47, 0.47)  # the other red block out of the way, far corner
    blocks[red_cube] = (0.35, 0.15)
    sim = TabletopSim()
    sim.place(blocks, (0.1, 0.3))
    frame = torch.from_numpy(Renderer(size).render(sim.scene()))[None]
    encoder = ObjectMapEncoder(
        Feature(CAMERA, "image", "uint8", (size, size, 3)), {"pooling": "keypoints", "keypoints": 3}
    )
    assert encoder.out_dim == 6
    patch_conv, _, mix_conv, _, detector = encoder.convs
    with torch.no_grad():
        for conv in (patch_conv, mix_conv, detector):
            conv.weight.zero_()
            conv.bias.zero_()
        patch_conv.weight[0, COLOURS.index("red")] = 1.0  # channel 0: red pixels in the patch
        mix_conv.weight[0, 0, 1, 1] = 1.0
        detector.weight[0, 0] = 30.0  # sharp: the softmax keeps the bright patches only
    # Blank out the far red block so that keypoint 0 sees one blob.
    far = _pixel((0.47, 0.47), size)
    frame[0, : round(far[0]) + 6, round(far[1]) - 6 :] = 0
    coordinates = encoder(frame)[0].detach().numpy()
    row, column = _pixel((0.35, 0.15), size)
    expected = (column / (size - 1) * 2 - 1, row / (size - 1) * 2 - 1)
    np.testing.assert_allclose(coordinates[:2], expected, atol=0.06)
    assert np.abs(coordinates).max() <= 1.0


@pytest.mark.slow
def test_blocks_pooling_finds_every_block_and_pairs_each_colours_blocks() -> None:
    """Random layouts: the entities 2c and 2c + 1 are the two blocks of colour c (in either order), each
    within 0.06 of the true image position (a patch is 0.087); no learning involved."""
    from playseg_core.domains.tabletop.evaluation import evaluation_start
    from playseg_core.domains.tabletop.spec import SHAPES

    size = 96
    encoder = ObjectMapEncoder(Feature(CAMERA, "image", "uint8", (size, size, 3)), {"pooling": "blocks"})
    renderer = Renderer(size)
    assert encoder.out_dim == 2 * len(BLOCKS) and encoder.entity_dim == 32
    worst = 0.0
    for seed in range(40):
        scene = evaluation_start(seed)[0].scene()
        pooled, entities, positions = encoder.encode_with_entities(
            torch.from_numpy(renderer.render(scene))[None]
        )
        assert entities.shape == (1, len(BLOCKS), 32) and positions.shape == (1, len(BLOCKS), 2)
        np.testing.assert_array_equal(pooled[0].detach().numpy(), positions[0].flatten().detach().numpy())
        found = positions[0].detach().numpy()
        for c, colour in enumerate(COLOURS):
            truth = []
            for shape in SHAPES:
                row, column = _pixel(tuple(scene.blocks[BLOCKS.index(f"{colour} {shape}")]), size)
                truth.append((column / (size - 1) * 2 - 1, row / (size - 1) * 2 - 1))
            pair = found[len(SHAPES) * c : len(SHAPES) * (c + 1)]
            error = min(np.abs(pair - truth).max(), np.abs(pair[::-1] - truth).max())
            worst = max(worst, float(error))
    assert worst < 0.06, worst


@pytest.mark.slow
@pytest.mark.parametrize("size", [96, 192])  # 192: the masks pooled to the spreads' resolution
def test_blocks_pooling_by_size_tells_each_colours_cube_from_its_cylinder(size: int) -> None:
    """With ``twins_by_size`` the entity 2c + k is colour c's block of shape SHAPES[k], found by its
    spread in pixels: on 40 random layouts at most one of the 160 pairs comes out swapped (touching
    twins), every other block within 0.06 of its position; and the identities are one per block. The
    frames it reads are left as they were."""
    from playseg_core.domains.tabletop.evaluation import evaluation_start
    from playseg_core.domains.tabletop.spec import SHAPES

    feature = Feature(CAMERA, "image", "uint8", (size, size, 3))
    encoder = ObjectMapEncoder(feature, {"pooling": "blocks", "twins_by_size": True})
    assert encoder.identity.shape == (len(BLOCKS), 32)
    renderer = Renderer(size)
    swapped, worst = 0, 0.0
    for seed in range(40):
        scene = evaluation_start(seed)[0].scene()
        rendered = renderer.render(scene)
        frame = torch.from_numpy(rendered.copy())[None]
        found = encoder(frame)[0].view(len(BLOCKS), 2).detach().numpy()
        np.testing.assert_array_equal(frame[0].numpy(), rendered)
        np.testing.assert_array_equal(found, encoder.encode_with_entities(frame)[2][0].detach().numpy())
        for c, colour in enumerate(COLOURS):
            truth = []
            for shape in SHAPES:
                row, column = _pixel(tuple(scene.blocks[BLOCKS.index(f"{colour} {shape}")]), size)
                truth.append((column / (size - 1) * 2 - 1, row / (size - 1) * 2 - 1))
            error = float(np.abs(found[len(SHAPES) * c : len(SHAPES) * (c + 1)] - truth).max())
            if error > 0.06:
                swapped += 1
            else:
                worst = max(worst, error)
    assert swapped <= 1 and worst < 0.06, (swapped, worst)


def test_bad_pooling_settings_are_named() -> None:
    with pytest.raises(FeatureError, match="pooling must be 'grid', 'keypoints' or 'blocks'.*'mean'"):
        ObjectMapEncoder(Feature(CAMERA, "image", "uint8", (96, 96, 3)), {"pooling": "mean"})
    with pytest.raises(FeatureError, match="position_scale must be > 0, and other than 1 only with pooling"):
        ObjectMapEncoder(
            Feature(CAMERA, "image", "uint8", (96, 96, 3)), {"pooling": "grid", "position_scale": 2.0}
        )
    with pytest.raises(FeatureError, match="blob_iterations must be >= 1, got 0"):
        ObjectMapEncoder(
            Feature(CAMERA, "image", "uint8", (96, 96, 3)), {"pooling": "blocks", "blob_iterations": 0}
        )


def test_the_encoder_refuses_a_frame_it_cannot_read() -> None:
    with pytest.raises(FeatureError, match=f"{KIND}: feature 'observation.images.top'.*at least 16x16"):
        ObjectMapEncoder(Feature(CAMERA, "image", "uint8", (12, 96, 3)), {})


def test_the_domain_chooses_the_scaled_blocks_and_the_linear_head_and_checkpoints_keep_them(
    tmp_path: Path,
) -> None:
    features = PlayConfig().features
    instructions = ["push the red cube left", "push the blue cube right", "move the arm to the centre"]
    episode = tabletop_shaped_episode(10)
    config = model_config_for(features, DOMAIN, len(instructions), episodes=[episode])
    blocks = ObjectMapConfig(pooling="blocks", twins_by_size=True, position_scale=BLOCK_POSITION_SCALE)
    assert config.encoders[0] == object_map_spec(features[CAMERA], blocks) and config.label_head == "linear"
    # the generic state encoder, read as measured values, standardised with the training data's statistics
    state = config.encoders[1]
    assert state.kind == "state_mlp" and state.config["measured"] is True
    np.testing.assert_allclose(state.config["mean"], episode.state.mean(axis=0), rtol=1e-5)
    assert model_config_for(features, DOMAIN, 3, episodes=[episode], label_head="text").label_head == "text"
    torch.manual_seed(0)
    model = PSModel(config, instructions).eval()
    save_model(tmp_path / "m.pt", model)
    loaded, _ = load_model(tmp_path / "m.pt")
    assert loaded.cfg.label_head == "linear"
    frames = torch.from_numpy(episode.images[CAMERA][:4].copy())
    scaled = loaded.encoders.encoders[0](frames)
    unscaled = ObjectMapEncoder(features[CAMERA], {"pooling": "blocks", "twins_by_size": True})(frames)
    torch.testing.assert_close(scaled, unscaled * BLOCK_POSITION_SCALE)
    hidden = torch.randn(5, config.trunk.hidden_dim)
    torch.testing.assert_close(loaded.label_head(hidden), model.label_head(hidden))


def test_the_trunk_reads_the_blocks_through_periodic_embeddings_and_segmenting_scores_as_training(
    tmp_path: Path,
) -> None:
    features = PlayConfig().features
    instructions = ["push the red cube left", "push the blue cube right", "move the arm to the centre"]
    episode = tabletop_shaped_episode(12)
    config = model_config_for(features, DOMAIN, len(instructions), episodes=[episode], max_len=6)
    assert config.trunk.periodic_frequencies == PERIODIC_FREQUENCIES
    assert config.trunk.dropout == 0.0  # the domain's choice over the generic default
    torch.manual_seed(0)
    model = PSModel(config, instructions).eval()
    # measured values: the blocks' 16 coordinates, then the 4 state values the state encoder writes
    # before its learnt features (the action's columns come last and are not measured)
    measured = list(range(16 + 4))
    assert model.encoders.measured_columns == measured
    assert model.trunk.periodic is not None and model.trunk.periodic.columns.tolist() == measured
    # the distances between the 8 blocks' positions: 28 pairs, embedded to the trunk's width
    assert model.encoders.position_columns == [(2 * k, 2 * k + 1) for k in range(8)]
    assert model.pair_distances is not None and len(model.pair_distances.pairs) == 28
    assert model.step_dim == model.encoders.step_dim + config.trunk.hidden_dim
    state_encoder = model.encoders.encoders[1]
    rows = torch.from_numpy(episode.state[:3])
    standardised = (rows - state_encoder.mean) / state_encoder.std
    torch.testing.assert_close(state_encoder(rows)[:, :4], standardised)
    assert state_encoder.out_dim == 4 + 64
    with torch.no_grad():
        step_features = model.encode_episode(episode)
        matrix = model.end_logits(step_features)
        # the end matrix (windows made by forward_over_steps) is what one window through the trunk gives
        lookahead = model.lookahead
        padded = torch.cat([step_features, step_features.new_zeros(lookahead, step_features.shape[1])])
        for t in range(1, episode.num_steps + 1):
            window = padded[max(0, t - model.max_len) : t + 1 + lookahead]
            column = model.end_column(window, starts_episode=t <= model.max_len)
            for k in range(min(t, model.max_len)):
                torch.testing.assert_close(column[k], matrix[t - k - 1, k], rtol=1e-4, atol=1e-4)
        # the live segmenter's incremental scorer gives the same columns
        scorer = IncrementalEndScorer(model)
        for t in range(episode.num_steps + 1 + lookahead):
            scorer.push(padded[t])
            end = t - lookahead
            if end >= 1:
                column = scorer.column(max(0, end - model.max_len))
                for k in range(min(end, model.max_len)):
                    torch.testing.assert_close(column[k], matrix[end - k - 1, k], rtol=1e-4, atol=1e-4)
        # the embeddings take part: without their projection the logits differ
        saved = model.trunk.periodic.proj.weight.clone()
        model.trunk.periodic.proj.weight.zero_()
        assert not torch.allclose(model.end_logits(step_features), matrix)
        model.trunk.periodic.proj.weight.copy_(saved)
        saved = model.pair_distances.embed.weight.clone()
        model.pair_distances.embed.weight.zero_()
        assert not torch.allclose(model.end_logits(model.encode_episode(episode)), matrix)
        model.pair_distances.embed.weight.copy_(saved)
    save_model(tmp_path / "m.pt", model)
    loaded, _ = load_model(tmp_path / "m.pt")
    assert loaded.cfg.trunk.periodic_frequencies == loaded.cfg.trunk.pair_frequencies == PERIODIC_FREQUENCIES
    with torch.no_grad():
        torch.testing.assert_close(loaded.end_logits(loaded.encode_episode(episode)), matrix)


def test_the_distances_embedding_reads_the_distances_between_positions_only() -> None:
    """Moving, turning or mirroring every position together changes nothing; one pair's distance does,
    and a pair's own vector tells the pairs apart."""
    torch.manual_seed(0)
    embedding = PairDistanceEmbedding([(0, 1), (2, 3), (4, 5)], frequencies=8, out_dim=16)
    with torch.no_grad():
        embedding.pair.normal_()
    rows = torch.randn(5, 7)  # three positions, then a column that is not one
    angle = torch.tensor(0.7)
    turn = torch.stack([torch.stack([angle.cos(), -angle.sin()]), torch.stack([angle.sin(), angle.cos()])])
    moved = rows.clone()
    points = rows[:, :6].reshape(5, 3, 2) @ turn.T * torch.tensor([-1.0, 1.0]) + torch.tensor([0.3, -2.0])
    moved[:, :6] = points.reshape(5, 6)
    moved[:, 6] = 5.0
    torch.testing.assert_close(embedding(moved), embedding(rows), atol=1e-4, rtol=1e-4)
    apart = rows.clone()
    apart[:, 4:6] += 3.0  # the third thing moves away from the other two
    assert not torch.allclose(embedding(apart), embedding(rows), atol=1e-3)
    distances = embedding.distances(rows)
    torch.testing.assert_close(distances[:, 0], (rows[:, 0:2] - rows[:, 2:4]).norm(dim=-1))
    swapped = PairDistanceEmbedding([(0, 1), (4, 5), (2, 3)], frequencies=8, out_dim=16)
    swapped.load_state_dict(embedding.state_dict())
    assert not torch.allclose(swapped(rows), embedding(rows), atol=1e-3)


@pytest.mark.slow
def test_a_text_head_labels_combinations_never_seen_in_training() -> None:
    colours, directions = ["red", "blue", "green", "yellow"], ["left", "right", "up", "down"]
    instructions = [f"push the {c} block {d}" for c in colours for d in directions]
    unseen = {f"push the {c} block {d}" for c, d in zip(colours, directions, strict=True)}
    rng = np.random.default_rng(0)

    def features(indices: np.ndarray) -> torch.Tensor:
        colour, direction = indices // 4, indices % 4
        rows = np.zeros((len(indices), 8), np.float32)
        rows[np.arange(len(indices)), colour] = 1.0
        rows[np.arange(len(indices)), 4 + direction] = 1.0
        return torch.from_numpy(rows + rng.normal(0, 0.1, rows.shape).astype(np.float32))

    seen = np.array([i for i, text in enumerate(instructions) if text not in unseen])
    held_out = np.array([i for i, text in enumerate(instructions) if text in unseen])
    accuracy = {}
    for kind in ("text", "linear"):
        torch.manual_seed(0)
        head = make_label_head(kind, 8, instructions)
        optimizer = torch.optim.Adam(head.parameters(), lr=0.02)
        for _ in range(300):
            labels = rng.choice(seen, 64)
            loss = torch.nn.functional.cross_entropy(head(features(labels)), torch.from_numpy(labels))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        test = np.repeat(held_out, 25)
        predicted = head(features(test)).argmax(-1).numpy()
        accuracy[kind] = float((predicted == test).mean())
    assert accuracy["text"] > 0.8, accuracy
    assert accuracy["linear"] < 0.2, accuracy


def test_a_text_head_s_tokens_are_the_ones_its_checkpoints_hold() -> None:
    """The text head's vocabulary is rebuilt from the instructions when a checkpoint loads, so it must
    stay what it was: words, words at their positions, adjacent pairs; an instruction without words is
    itself at position 0."""
    from playseg_core.ps.model import instruction_tokens

    assert instruction_tokens("Push the red cube") == [
        "push", "the", "red", "cube", "0:push", "1:the", "2:red", "3:cube",
        "push the", "the red", "red cube",
    ]  # fmt: skip
    head = TextLabelHead(8, ["拿起红色方块", "go left"])
    assert head.token_embedding.shape[0] == 7  # 2 for the first, go, left, 0:go, 1:left, "go left"


@pytest.mark.parametrize("pooling", ["blocks", "grid", "keypoints"])
def test_the_camera_encoder_makes_its_tensors_on_its_own_device(pooling: str) -> None:
    """PS and the baselines move the encoder to a GPU wherever torch sees one: a tensor it makes on the
    CPU inside its forward would fail there. The meta device stands in for the GPU (the same rule)."""
    features = PlayConfig().features
    spec = object_map_spec(features[CAMERA], ObjectMapConfig(pooling=pooling, twins_by_size=True))
    encoder = StepEncoders([spec], features).encoders[0].to("meta")
    frames = torch.zeros((2, *features[CAMERA].shape), dtype=torch.uint8, device="meta")
    rows = encoder(frames)
    assert rows.device.type == "meta" and rows.shape[0] == 2
