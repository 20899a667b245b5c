"""The square table's 8 symmetries (playseg_core/domains/tabletop/symmetry.py): a transformed frame is
the frame of the transformed table, and a transformed instruction is done exactly when the original is,
on the transformed scenes; the policy trains with them (``augment``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from playseg_core.augment.policies import load_policy_learner
from playseg_core.data.episode import Episode, Segment, SegmentClip
from playseg_core.data.features import ACTION, STATE
from playseg_core.domains import tabletop
from playseg_core.domains.tabletop.instructions import INSTRUCTIONS, is_done, task_for
from playseg_core.domains.tabletop.render import Renderer
from playseg_core.domains.tabletop.sim import Scene, TabletopSim
from playseg_core.domains.tabletop.spec import BLOCKS, CAMERA, COLOUR_RGB, EFFECTOR_RGB
from playseg_core.domains.tabletop.symmetry import (
    SYMMETRIES,
    apply_symmetries,
    random_symmetry,
    symmetry_matrix,
    transform_frames,
    transform_instruction,
    transform_points,
)


def tiny_clip() -> SegmentClip:
    """A short recorded clip: the tabletop's own features (96x96 frames, 4-D state, 2-D commands)."""
    rng = np.random.default_rng(3)
    return SegmentClip(
        episode_id="e0",
        segment=Segment(0, 6, "push the red cube left"),
        actions=rng.uniform(-0.2, 0.2, (6, 2)).astype(np.float32),
        images={CAMERA: rng.integers(0, 255, (7, 96, 96, 3), dtype=np.uint8)},
        state=rng.uniform(0, 0.5, (7, 4)).astype(np.float32),
        source="annotation",
    )


def scene_of(blocks: np.ndarray, effector: np.ndarray, angles: np.ndarray) -> Scene:
    sim = TabletopSim()
    sim.place(blocks, effector, angles)
    return sim.scene()


def transformed_scene(scene: Scene, quarter_turns: int, mirror: bool) -> Scene:
    matrix = symmetry_matrix(quarter_turns, mirror)
    angles = (-scene.angles if mirror else scene.angles) + quarter_turns * math.pi / 2
    return scene_of(transform_points(scene.blocks, matrix), transform_points(scene.effector, matrix), angles)


@pytest.mark.parametrize(("quarter_turns", "mirror"), SYMMETRIES)
def test_a_transformed_frame_is_the_frame_of_the_transformed_table(quarter_turns: int, mirror: bool) -> None:
    rng = np.random.default_rng(quarter_turns + 4 * mirror)
    sim = TabletopSim()
    sim.place_randomly(rng)
    scene = sim.scene()
    renderer = Renderer(96)
    expected = renderer.render(transformed_scene(scene, quarter_turns, mirror)).astype(int)
    turned = transform_frames(renderer.render(scene)[None], quarter_turns, mirror)[0].astype(int)
    # OpenCV's anti-aliased rectangle shades the table's rim differently on opposite sides (a pixel line
    # or two): the rim is left out. Elsewhere only shapes' edge pixels may be shaded differently, and
    # each colour lies where it should within a pixel (anti-aliasing is not symmetric either).
    background = renderer._background.astype(int)
    rim = np.abs(transform_frames(background[None], quarter_turns, mirror)[0] - background).max(-1) > 0
    assert rim.mean() < 0.08
    differs = np.abs(turned - expected).max(-1) > 8
    assert differs[~rim].mean() < 0.03, differs[~rim].sum()
    rows, columns = np.mgrid[0:96, 0:96]
    for colour in [*COLOUR_RGB.values(), EFFECTOR_RGB]:
        centres = []
        for frame in (turned, expected):
            mask = (np.abs(frame - np.array(colour)).max(-1) < 30) & ~rim
            centres.append(
                (float((mask * rows).sum() / mask.sum()), float((mask * columns).sum() / mask.sum()))
            )
        np.testing.assert_allclose(centres[0], centres[1], atol=1.0)


@pytest.mark.slow
@pytest.mark.parametrize(("quarter_turns", "mirror"), SYMMETRIES[1:])
def test_a_transformed_instruction_is_done_when_the_original_is(quarter_turns: int, mirror: bool) -> None:
    rng = np.random.default_rng(7)
    matrix = symmetry_matrix(quarter_turns, mirror)
    changed, agreements, done_pairs = 0, 0, 0
    for _ in range(40):
        start, end = TabletopSim(), TabletopSim()
        start.place_randomly(rng)
        end.place_randomly(rng)
        # The end: the start's blocks moved a little, so that some tasks are done and some not.
        moved = start.scene().blocks + rng.normal(0, 0.06, (len(BLOCKS), 2))
        end_scene = scene_of(np.clip(moved, 0.03, 0.47), end.scene().effector, start.scene().angles)
        for text in rng.choice(INSTRUCTIONS, size=20, replace=False):
            task = task_for(str(text))
            turned = task_for(transform_instruction(task.text, matrix))
            changed += turned.text != task.text
            done = is_done(task, end_scene, start.scene())
            turned_done = is_done(
                turned,
                transformed_scene(end_scene, quarter_turns, mirror),
                transformed_scene(start.scene(), quarter_turns, mirror),
            )
            agreements += done == turned_done
            done_pairs += done
    assert agreements == 40 * 20
    assert done_pairs >= 20, done_pairs  # both outcomes occur
    assert changed > 100  # regions and directions did turn


def test_words_follow_the_table() -> None:
    quarter = symmetry_matrix(1, False)
    assert transform_instruction("push the red cube left", quarter) == "push the red cube down"
    assert transform_instruction("move the arm to the top left corner", quarter) == (
        "move the arm to the bottom left corner"
    )
    mirror = symmetry_matrix(0, True)
    assert transform_instruction("push the blue cylinder to the right edge", mirror) == (
        "push the blue cylinder to the left edge"
    )
    assert transform_instruction("separate the red cube from the blue cube", quarter) == (
        "separate the red cube from the blue cube"
    )
    assert transform_instruction("wave hello", quarter) == "wave hello"


def test_each_sample_moves_as_one_under_its_own_symmetry() -> None:
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (16, 96, 96, 3), dtype=np.uint8)
    state = rng.uniform(0, 0.5, (16, 4)).astype(np.float32)
    actions = rng.uniform(-0.2, 0.2, (16, 2)).astype(np.float32)
    texts = [str(t) for t in rng.choice(INSTRUCTIONS, size=16)]
    kept = (frames.copy(), state.copy(), actions.copy(), list(texts))
    chosen = np.arange(16) % len(SYMMETRIES)
    observations, instructions, turned = apply_symmetries(
        {CAMERA: frames, STATE: state}, texts, actions, chosen
    )
    for i, (quarter_turns, mirror) in enumerate(SYMMETRIES[c] for c in chosen):
        matrix = symmetry_matrix(quarter_turns, mirror)
        np.testing.assert_array_equal(
            observations[CAMERA][i], transform_frames(frames[i : i + 1], quarter_turns, mirror)[0]
        )
        np.testing.assert_allclose(
            observations[STATE][i, :2], transform_points(state[i, :2], matrix), atol=1e-6
        )
        np.testing.assert_allclose(observations[STATE][i, 2:], matrix @ state[i, 2:], atol=1e-6)
        np.testing.assert_allclose(turned[i], matrix @ actions[i], atol=1e-6)
        assert instructions[i] == transform_instruction(texts[i], matrix)
    # The identity leaves a sample as it was; the inputs are not touched.
    np.testing.assert_array_equal(observations[CAMERA][0], frames[0])
    for before, after in zip(kept, (frames, state, actions, texts), strict=True):
        np.testing.assert_array_equal(np.asarray(before), np.asarray(after))
    # Random draws differ between samples: all four direction words come up.
    _, drawn, _ = random_symmetry(
        {CAMERA: frames, STATE: state}, ["push the red cube left"] * 16, actions, np.random.default_rng(1)
    )
    assert len(set(drawn)) == 4


def test_the_policy_trains_with_the_symmetries_and_the_generic_one_refuses_them() -> None:
    learner = load_policy_learner("tabletop.bc", {"augment": True, "steps": 2, "batch_size": 4})
    assert learner.bc.settings.augment and learner.bc.sample_symmetry is random_symmetry
    calls = []

    def counted(*batch):
        calls.append(len(batch[1]))
        return random_symmetry(*batch)

    learner.bc.sample_symmetry = counted
    clip = tiny_clip()
    _, report = learner.train([clip, clip])
    assert calls == [4, 4] and report.steps == 2
    with pytest.raises(ValueError, match="augment needs the symmetries of the data's world"):
        load_policy_learner("bc", {"augment": True}, features=learner.features)


def test_a_segmentation_clip_turns_as_one_with_its_instruction() -> None:
    """PS's training clips (``playseg train --augment``, the domain's CLIP_SYMMETRIES): every row of a clip
    under the same symmetry, the one `apply_symmetries` gives, with the instruction turned; a clip without
    some features is fine, and the recorded arrays are left as they were."""
    symmetries = tabletop.CLIP_SYMMETRIES
    assert symmetries.count == len(SYMMETRIES)
    rng = np.random.default_rng(0)
    clip = {
        CAMERA: rng.integers(0, 255, (9, 96, 96, 3), dtype=np.uint8),
        STATE: rng.uniform(0, 0.5, (9, 4)).astype(np.float32),
        ACTION: rng.uniform(-0.2, 0.2, (9, 2)).astype(np.float32),
    }
    kept = {feature: array.copy() for feature, array in clip.items()}
    texts = set()
    for number in range(symmetries.count):
        turned = symmetries.turn_clip(clip, number)
        text = symmetries.turn_instruction("push the red cube left", number)
        expected, words, actions = apply_symmetries(
            {CAMERA: clip[CAMERA], STATE: clip[STATE]}, ["push the red cube left"] * 9, clip[ACTION],
            np.full(9, number),
        )  # fmt: skip
        np.testing.assert_array_equal(turned[CAMERA], expected[CAMERA])
        np.testing.assert_allclose(turned[STATE], expected[STATE], atol=1e-6)
        np.testing.assert_allclose(turned[ACTION], actions, atol=1e-6)
        assert text == words[0]
        texts.add(text)
    assert texts == {f"push the red cube {d}" for d in ("left", "right", "up", "down")}
    for feature, array in kept.items():
        np.testing.assert_array_equal(clip[feature], array)
    only_camera = symmetries.turn_clip({CAMERA: clip[CAMERA]}, 3)
    assert set(only_camera) == {CAMERA}
    assert symmetries.turn_instruction("move the arm to the centre", 3) == "move the arm to the centre"


def test_ps_trains_on_turned_clips_with_turned_labels() -> None:
    """make_batch with the domain's CLIP_SYMMETRIES: a model that reads the commands may augment, and each
    segment's label is its turned instruction's class."""
    from playseg_core.domains.tabletop.play import PlayConfig
    from playseg_core.ps.model import PSModel
    from playseg_core.ps.samples import label_index, make_batch
    from playseg_core.ps.training import clip_symmetries_of, model_config_for

    assert clip_symmetries_of("tabletop") is tabletop.CLIP_SYMMETRIES and clip_symmetries_of(None) is None
    rng = np.random.default_rng(1)
    steps = 30
    episode = Episode(
        "e",
        rng.uniform(-0.2, 0.2, (steps, 2)).astype(np.float32),
        {CAMERA: rng.integers(0, 255, (steps + 1, 96, 96, 3), dtype=np.uint8)},
        rng.uniform(0, 0.5, (steps + 1, 4)).astype(np.float32),
        segments=[Segment(2, 12, "push the red cube left"), Segment(14, 28, "move the arm to the top edge")],
    )
    classes = label_index(list(INSTRUCTIONS))
    config = model_config_for(
        PlayConfig().features, "tabletop", len(INSTRUCTIONS), max_len=20, episodes=[episode]
    )
    model = PSModel(config, list(INSTRUCTIONS))
    assert model.encoders.reads_actions
    items = [(episode, segment) for segment in episode.segments]
    seen = set()
    for seed in range(24):
        batch = make_batch(
            items, classes, model.encoders, 20, 2, np.random.default_rng(seed),
            symmetries=tabletop.CLIP_SYMMETRIES,
        )  # fmt: skip
        words = [INSTRUCTIONS[int(label)] for label in batch.labels]
        assert all(
            task_for(word).family == task_for(s.instruction).family
            for word, s in zip(words, episode.segments, strict=True)
        )
        seen.update(words)
        # The first clip's first frame is the recorded frame under the symmetry its label says.
        first = batch.inputs[CAMERA][0].numpy()
        matches = [
            (k, m) for k, m in SYMMETRIES
            if transform_instruction("push the red cube left", symmetry_matrix(k, m)) == words[0]
            and np.array_equal(transform_frames(episode.images[CAMERA][:1], k, m)[0], first)
        ]  # fmt: skip
        assert matches, words[0]
    assert len({w for w in seen if w.startswith("push the red cube")}) == 4
    assert len({w for w in seen if w.startswith("move the arm")}) > 1


def random_layout_frames(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` camera frames of the table, the blocks in a new random layout in each: real blocks to
    find."""
    renderer, sim, frames = Renderer(96), TabletopSim(), []
    for _ in range(count):
        sim.place_randomly(rng)
        frames.append(renderer.render(sim.scene()))
    return np.stack(frames)


def random_layout_episode(
    rng: np.random.Generator, steps: int, segments: list[Segment] | None = None
) -> Episode:
    """An episode of ``steps`` random commands over `random_layout_frames`, with a random state."""
    return Episode(
        "e",
        rng.uniform(-0.2, 0.2, (steps, 2)).astype(np.float32),
        {CAMERA: random_layout_frames(rng, steps + 1)},
        rng.uniform(0, 0.5, (steps + 1, 4)).astype(np.float32),
        segments=segments or [],
    )


@pytest.mark.slow
def test_the_blocks_are_encoded_once_per_episode_and_symmetry() -> None:
    """The blocks' positions learn nothing: training encodes them once per (episode, symmetry) and reads
    rows from there (ps/fixed_features.py). The step encoders' rows of such a batch are those of the batch that
    carries the turned frames, and the state and commands still come as input rows."""
    from playseg_core.domains.tabletop.play import PlayConfig
    from playseg_core.ps.fixed_features import FixedFeatureCache
    from playseg_core.ps.model import PSModel
    from playseg_core.ps.samples import label_index, make_batch
    from playseg_core.ps.training import model_config_for

    episode = random_layout_episode(
        np.random.default_rng(2),
        30,
        [Segment(2, 12, "push the red cube left"), Segment(14, 28, "move the arm to the top edge")],
    )
    config = model_config_for(
        PlayConfig().features, "tabletop", len(INSTRUCTIONS), max_len=20, episodes=[episode]
    )
    model = PSModel(config, list(INSTRUCTIONS)).eval()
    fixed = FixedFeatureCache(model.encoders)
    assert fixed.features == [CAMERA]
    items, classes = [(episode, segment) for segment in episode.segments], label_index(list(INSTRUCTIONS))
    with torch.no_grad():
        for seed in range(6):
            plain, cached = (
                make_batch(
                    items, classes, model.encoders, 20, 2, np.random.default_rng(seed),
                    symmetries=tabletop.CLIP_SYMMETRIES, fixed=cache,
                )
                for cache in (None, fixed)
            )  # fmt: skip
            assert CAMERA not in cached.inputs and set(cached.encoded) == {CAMERA}
            assert set(cached.inputs) == set(plain.inputs) - {CAMERA}
            torch.testing.assert_close(cached.labels, plain.labels)
            torch.testing.assert_close(cached.window_index, plain.window_index)
            # the step encoders' rows (the distances' embedding, learnt, is made from them in every batch)
            torch.testing.assert_close(
                model.encoders(cached.inputs, cached.encoded), model.encoders(plain.inputs), atol=1e-5, rtol=0
            )
            torch.testing.assert_close(
                model.encode_steps(cached.inputs, cached.encoded),
                model.encode_steps(plain.inputs),
                atol=1e-4,
                rtol=0,
            )
    assert 2 <= len(fixed) <= len(SYMMETRIES)  # one episode, the symmetries drawn so far
    # Another episode under the same id (lists given to training need not come from one dataset) gets
    # its own rows, not the first one's.
    namesake = Episode(
        "e", episode.actions, {CAMERA: np.ascontiguousarray(episode.images[CAMERA][::-1])}, episode.state
    )
    with torch.no_grad():
        expected = model.encoders.encoders[0](torch.from_numpy(namesake.images[CAMERA][:4].copy()))
    torch.testing.assert_close(fixed.clip_rows(namesake, 0, 3)[CAMERA], expected, atol=1e-5, rtol=0)


def test_the_window_baselines_read_the_blocks_from_the_cache() -> None:
    """UnLoc and TriDet train on windows of raw steps: the blocks' rows come from the cache of rows
    encoded once per episode (`window_inputs` with a `FixedFeatureCache`), and the step features of a
    batch equal those of the batch that carries the frames; the state and commands still come as input
    rows, and the padding repeats a window's last row either way."""
    from playseg_core.baselines.common import encode_windows, window_inputs
    from playseg_core.baselines.unloc import UnlocConfig, UnlocModel
    from playseg_core.domains.tabletop.play import PlayConfig
    from playseg_core.ps.fixed_features import FixedFeatureCache
    from playseg_core.ps.training import model_config_for

    episode = random_layout_episode(np.random.default_rng(3), 20)
    features = PlayConfig().features
    specs = model_config_for(features, "tabletop", 3, max_len=20, episodes=[episode]).encoders
    model = UnlocModel(specs, features, list(INSTRUCTIONS)[:3], UnlocConfig(length_counts={5: 1})).eval()
    fixed = FixedFeatureCache(model.encoders)
    assert fixed.features == [CAMERA]
    windows = [(episode, 0, 7), (episode, 4, 20), (episode, 12, 15)]
    plain, cached = window_inputs(model.encoders, windows), window_inputs(model.encoders, windows, fixed)
    assert CAMERA in plain.inputs and not plain.encoded
    assert CAMERA not in cached.inputs and set(cached.encoded) == {CAMERA}
    assert set(cached.inputs) == set(plain.inputs) - {CAMERA} and cached.inputs
    torch.testing.assert_close(cached.valid, plain.valid)
    with torch.no_grad():  # the cached rows padded as the frames are: each window's last row repeated
        camera = model.encoders.encoders[0]
        torch.testing.assert_close(cached.encoded[CAMERA], camera(plain.inputs[CAMERA]), atol=1e-5, rtol=0)
    with torch.no_grad():
        rows = encode_windows(model.encoders, cached)
        torch.testing.assert_close(rows, encode_windows(model.encoders, plain), atol=1e-5, rtol=0)
    assert rows.shape[:2] == (3, 17) and not rows[2, 4:].any()  # zero past the short window's rows
    assert len(fixed) == 1  # the episode encoded once for all three windows


def test_the_blocks_turn_as_the_table_without_encoding_the_turned_frames() -> None:
    """The blocks' rows of a turned clip are the recorded rows turned (`turn_block_rows`), equal to
    encoding the turned frames, so the cache encodes an episode's frames once for all 8 symmetries."""
    from playseg_core.domains.tabletop.encoder import ObjectMapConfig, object_map_spec
    from playseg_core.domains.tabletop.play import PlayConfig
    from playseg_core.domains.tabletop.symmetry import transform_frames, turn_block_rows
    from playseg_core.ps.encoders import StepEncoders
    from playseg_core.ps.fixed_features import FixedFeatureCache

    features = PlayConfig().features
    spec = object_map_spec(features[CAMERA], ObjectMapConfig(pooling="blocks", twins_by_size=True))
    rng = np.random.default_rng(5)
    frames = random_layout_frames(rng, 12)
    encoders = StepEncoders([spec], features)
    encoder = encoders.encoders[0]
    with torch.no_grad():
        recorded = encoder(torch.from_numpy(frames))
        for number, (quarter_turns, mirror) in enumerate(SYMMETRIES):
            turned = np.ascontiguousarray(transform_frames(frames, quarter_turns, mirror))
            expected = encoder(torch.from_numpy(turned))
            torch.testing.assert_close(turn_block_rows(spec, recorded, number), expected, atol=1e-5, rtol=0)
    # another encoder's rows are not the domain's to turn
    assert turn_block_rows(object_map_spec(features[CAMERA]), recorded, 1) is None

    calls = []
    original = encoder.forward
    encoder.forward = lambda rows: calls.append(len(rows)) or original(rows)
    episode = Episode("e", np.zeros((11, 2), np.float32), {CAMERA: frames})
    cache = FixedFeatureCache(encoders)
    with torch.no_grad():
        rows = [cache.clip_rows(episode, 0, 11, n, tabletop.CLIP_SYMMETRIES)[CAMERA] for n in range(8)]
    assert sum(calls) == len(frames)  # the recorded frames, once
    torch.testing.assert_close(rows[3], turn_block_rows(spec, recorded, 3))
