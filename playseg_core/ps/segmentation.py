"""End-to-end Play Segmentation of an episode: encode steps once, score all windows, decode, label.

`segment_episode`: T step encodings, batched trunk passes over the T windows (in chunks: time and memory
linear in T), the exact O(T * L_max) decoder of decoding.py, then the label head at each chosen end.
(The reference's cost model, for comparison, is in reference_style.py.)
"""

from __future__ import annotations

import torch

from playseg_core.data.episode import Episode, Segment
from playseg_core.ps.decoding import decode_segments
from playseg_core.ps.model import PSModel


def labelled_segment(
    model: PSModel, start: int, end: int, label_logits: torch.Tensor, log_prob: float
) -> Segment:
    """The segment [start, end) labelled with the most probable instruction (confidence = its probability)."""
    probs = torch.softmax(label_logits.double(), dim=-1)
    best = int(probs.argmax())
    return Segment(start, end, model.instructions[best], float(probs[best]), float(log_prob))


@torch.no_grad()
def segment_episode(model: PSModel, episode: Episode, min_len: int = 1) -> list[Segment]:
    """The most likely segmentation of `episode` under `model`, each segment labelled by the label head.

    Segment.confidence is the label probability, Segment.log_prob the segment's log-score log s(i, j).
    """
    model.eval()
    if episode.num_steps == 0:
        return []
    features = model.encode_episode(episode)
    end_logits = model.end_logits(features).double().cpu().numpy()
    max_len = min(model.max_len, episode.num_steps)
    min_len = min(min_len, max_len)  # an episode shorter than L_min is one segment
    decoded = decode_segments(end_logits[:, :max_len], min_len=min_len, max_len=max_len)
    label_logits = model.segment_label_logits(features, decoded.segments)
    return [
        labelled_segment(model, start, end, logits, log_prob)
        for (start, end), logits, log_prob in zip(
            decoded.segments, label_logits, decoded.segment_log_scores, strict=True
        )
    ]
