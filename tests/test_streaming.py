"""Segmenting a stream frame by frame gives exactly the offline segmentation and keeps only undecided frames."""

import pytest
import torch

from playseg_core.babyai import INSTRUCTIONS, PlayConfig, generate_episode
from playseg_core.models import PSModel
from playseg_core.segmentation import segment_episode
from playseg_core.streaming import StreamingSegmenter
from playseg_core.training import default_model_config


@pytest.mark.parametrize("seed", [0, 1])
def test_stream_equals_offline(seed):
    torch.manual_seed(seed)  # untrained weights cut arbitrarily: many boundaries to compare
    model = PSModel(default_model_config(len(INSTRUCTIONS)), list(INSTRUCTIONS))
    episode = generate_episode(PlayConfig(), 40 + seed)
    stream = StreamingSegmenter(model)
    live = []
    for frame in episode.frames:
        live += stream.push(frame)
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
