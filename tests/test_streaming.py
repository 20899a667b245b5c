"""Segmenting a stream frame by frame gives exactly the offline segmentation and keeps only undecided frames."""

import pytest
import torch

from playseg_core.data.episode import Episode
from playseg_core.data.features import STATE
from playseg_core.domains.babyai.play import PlayConfig, generate_episode
from playseg_core.domains.babyai.spec import CAMERA, DOMAIN, INSTRUCTIONS
from playseg_core.ps.model import PSModel
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.ps.training import model_config_for


def babyai_model(read_actions: bool, end_lookahead: int = 0) -> PSModel:
    cfg = model_config_for(
        PlayConfig().features,
        DOMAIN,
        len(INSTRUCTIONS),
        read_actions=read_actions,
        end_lookahead=end_lookahead,
    )
    return PSModel(cfg, list(INSTRUCTIONS))


def assert_live_equals_offline(live: list, offline: list, num_steps: int) -> None:
    """The same segments and labels, their scores up to float rounding, the last ending the episode."""
    assert [(s.start, s.end, s.instruction) for s in live] == [
        (s.start, s.end, s.instruction) for s in offline
    ]
    assert [s.confidence for s in live] == pytest.approx([s.confidence for s in offline], abs=1e-5)
    assert [s.log_prob for s in live] == pytest.approx([s.log_prob for s in offline], abs=1e-4)
    assert live[-1].end == num_steps


@pytest.mark.parametrize(
    ("seed", "read_actions", "end_lookahead"),
    [(0, False, 0), (1, False, 0), (2, True, 0), (3, True, 1), (4, False, 3)],
)
@pytest.mark.slow
def test_stream_equals_offline(seed, read_actions, end_lookahead):
    torch.manual_seed(seed)  # untrained weights cut arbitrarily: many boundaries to compare
    model = babyai_model(read_actions, end_lookahead)
    episode = generate_episode(PlayConfig(), 40 + seed)
    stream = StreamingSegmenter(model)
    live = []
    for t, frame in enumerate(episode.images[CAMERA]):
        # as a PlayStep carries them: o_t with a_t, the last observation without an action
        observation = {CAMERA: frame, STATE: episode.state[t]}
        live += stream.push(observation, episode.actions[t] if t < episode.num_steps else None)
        # only frames from the last decided boundary on are kept (older ones are never needed again)
        assert stream._offset == (live[-1].end if live else 0)
    live += stream.finish()
    assert_live_equals_offline(live, segment_episode(model, episode), episode.num_steps)


def test_stream_of_an_action_model_rejects_a_missing_or_invalid_action():
    torch.manual_seed(0)
    model = babyai_model(read_actions=True)
    episode = generate_episode(PlayConfig(), 40)
    frames = episode.images[CAMERA]
    stream = StreamingSegmenter(model)
    stream.push({CAMERA: frames[0]}, None)
    with pytest.raises(ValueError, match="observation 1: the previous step carried no action"):
        stream.push({CAMERA: frames[1]}, episode.actions[1])
    with pytest.raises(ValueError, match=r"action of step 0\[0\] = 9.0: not a discrete action index in 0..6"):
        StreamingSegmenter(model).push({CAMERA: frames[0]}, [9.0])
    with pytest.raises(ValueError, match=f"step 0: the model reads feature '{CAMERA}', the step lacks it"):
        StreamingSegmenter(model).push({STATE: episode.state[0]}, [1.0])


@pytest.mark.slow
@pytest.mark.parametrize("end_lookahead", [0, 2])
def test_an_episode_shorter_than_l_min_is_one_segment_live_as_offline(end_lookahead):
    torch.manual_seed(0)
    model = babyai_model(read_actions=True, end_lookahead=end_lookahead)
    model.cfg.min_len = 4
    episode = generate_episode(PlayConfig(), 3)
    for num_steps in (1, 3, 4, 6):
        stream, live = StreamingSegmenter(model, min_len=4), []
        for t in range(num_steps + 1):
            observation = {CAMERA: episode.images[CAMERA][t], STATE: episode.state[t]}
            live += stream.push(observation, episode.actions[t] if t < num_steps else None)
        live += stream.finish()  # an episode shorter than L_min used to fail here
        with pytest.raises(RuntimeError, match="finish called twice"):
            stream.finish()
        short = Episode(
            "short", episode.actions[:num_steps], {CAMERA: episode.images[CAMERA][: num_steps + 1]},
            state=episode.state[: num_steps + 1],
        )  # fmt: skip
        offline = segment_episode(model, short, min_len=4)
        assert [(s.start, s.end, s.instruction) for s in live] == [
            (s.start, s.end, s.instruction) for s in offline
        ]
        assert [s.log_prob for s in live] == pytest.approx([s.log_prob for s in offline], abs=1e-4)
        assert [s.confidence for s in live] == pytest.approx([s.confidence for s in offline], abs=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("end_lookahead", [0, 2])
def test_incremental_end_scores_equal_end_column(end_lookahead):
    """Each step's column from the windows' advanced state equals `end_column` on the kept rows, before
    and after the caller drops committed rows, and over zero rows past the episode's end."""
    from playseg_core.ps.incremental import IncrementalEndScorer

    torch.manual_seed(7)
    model = babyai_model(read_actions=False, end_lookahead=end_lookahead).eval()
    with torch.no_grad():
        model.end_bias.fill_(0.25)
    steps = model.max_len * 3
    features = torch.randn(steps, model.step_dim)
    if end_lookahead:  # zero rows past the episode's end, as `finish` pushes them
        features[-end_lookahead:] = 0.0
    scorer, first_kept, compared = IncrementalEndScorer(model), 0, 0
    for t in range(steps):
        scorer.push(features[t])
        if t == model.max_len + 10:
            first_kept = t - 12  # the caller committed everything before this row
        if t + 1 < 2 + end_lookahead:
            continue
        first_row = max(first_kept, t - (model.max_len + end_lookahead))
        expected = model.end_column(features[first_row : t + 1], first_row == 0)
        column = scorer.column(first_kept)
        assert torch.equal(torch.isfinite(column), torch.isfinite(expected)), t
        finite = torch.isfinite(expected)
        torch.testing.assert_close(column[finite], expected[finite], atol=1e-5, rtol=1e-5)
        compared += int(finite.sum())
    assert compared > steps * model.max_len // 2  # most of each column was scored


@pytest.mark.slow
def test_stream_of_a_model_reading_the_distances_between_blocks_equals_offline():
    """A tabletop model (the blocks' positions, their distances, periodic embeddings, the domain's end
    lookahead) on real generated play: live, frame by frame, as offline."""
    from playseg_core.domains.tabletop.play import PlayConfig as TabletopPlay
    from playseg_core.domains.tabletop.play import generate_episode as tabletop_episode
    from playseg_core.domains.tabletop.spec import CAMERA as TOP
    from playseg_core.domains.tabletop.spec import DOMAIN as TABLETOP

    play = TabletopPlay(tasks_per_episode=(3, 3))
    # a block pushed to the bottom edge, another next to a third: the distances between them change
    episode = tabletop_episode(play, 4).episode
    assert "push the red cylinder next to the blue cube" in {s.instruction for s in episode.segments}
    instructions = sorted({s.instruction for s in episode.segments} | {"move the arm to the centre"})
    cfg = model_config_for(play.features, TABLETOP, len(instructions), max_len=12, episodes=[episode])
    torch.manual_seed(0)  # untrained weights cut arbitrarily: many boundaries to compare
    model = PSModel(cfg, instructions).eval()
    assert model.pair_distances is not None and model.trunk.periodic is not None and model.lookahead > 0
    stream, live = StreamingSegmenter(model), []
    for t in range(episode.num_steps + 1):
        observation = {TOP: episode.images[TOP][t], STATE: episode.state[t]}
        live += stream.push(observation, episode.actions[t] if t < episode.num_steps else None)
    live += stream.finish()
    assert_live_equals_offline(live, segment_episode(model, episode), episode.num_steps)
