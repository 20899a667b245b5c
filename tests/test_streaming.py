"""Segmenting a stream frame by frame gives exactly the offline segmentation and keeps only undecided frames."""

import pytest
import torch

from playseg_core.domains.babyai.play import INSTRUCTIONS, NUM_ACTIONS, PlayConfig, generate_episode
from playseg_core.ps.model import PSModel
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.ps.training import default_model_config


@pytest.mark.parametrize(("seed", "num_actions"), [(0, 0), (1, 0), (2, NUM_ACTIONS)])
def test_stream_equals_offline(seed, num_actions):
    torch.manual_seed(seed)  # untrained weights cut arbitrarily: many boundaries to compare
    model = PSModel(default_model_config(len(INSTRUCTIONS), num_actions=num_actions), list(INSTRUCTIONS))
    episode = generate_episode(PlayConfig(), 40 + seed)
    stream = StreamingSegmenter(model)
    live = []
    for t, frame in enumerate(episode.frames):
        # as a PlayStep carries them: o_t with a_t, the last observation without an action
        live += stream.push(frame, episode.actions[t] if t < episode.num_steps else None)
        # only frames from the last decided boundary on are kept (older ones are never needed again)
        assert stream._offset == (live[-1].end if live else 0)
    live += stream.finish()
    offline = segment_episode(model, episode)
    assert [(s.start, s.end, s.instruction) for s in live] == [
        (s.start, s.end, s.instruction) for s in offline
    ]
    assert [s.confidence for s in live] == pytest.approx([s.confidence for s in offline], abs=1e-5)
    assert [s.log_prob for s in live] == pytest.approx([s.log_prob for s in offline], abs=1e-4)
    assert live[-1].end == episode.num_steps


def test_stream_of_an_action_model_rejects_a_missing_or_invalid_action():
    torch.manual_seed(0)
    model = PSModel(default_model_config(len(INSTRUCTIONS), num_actions=NUM_ACTIONS), list(INSTRUCTIONS))
    episode = generate_episode(PlayConfig(), 40)
    stream = StreamingSegmenter(model)
    stream.push(episode.frames[0], None)
    with pytest.raises(ValueError, match="observation 1: the previous step carried no action"):
        stream.push(episode.frames[1], episode.actions[1])
    with pytest.raises(ValueError, match=r"action of step 0\[0\] = 9.0: not a discrete action index in 0..6"):
        StreamingSegmenter(model).push(episode.frames[0], [9.0])
