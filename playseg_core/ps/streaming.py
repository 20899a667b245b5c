"""Play Segmentation of a stream: one episode fed step by step, segments emitted as soon as decided.

Each observation is encoded once; at step t the PS model scores every segment that could end at
e = t - lookahead (one column of the end-logit matrix, from the last L_max+1+lookahead step features,
each window's trunk state advanced by the new step: incremental.py; a model whose end head reads past
the end decides each end that many steps later, and at the episode's end reads zero rows there, as
offline) and the online decoder commits boundaries once every surviving
best path passes through them. The output equals `segment_episode` on the whole episode (same model,
same decoder recursion and tie rule).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from playseg_core.data.episode import Segment
from playseg_core.errors import PlaysegError
from playseg_core.ps.decoding import OnlineDecoder, decode_segments
from playseg_core.ps.encoders import as_tensors
from playseg_core.ps.incremental import IncrementalEndScorer
from playseg_core.ps.model import PSModel
from playseg_core.ps.segmentation import labelled_segment
from playseg_core.training.device import to_device


class StreamingSegmenter:
    """Segments one episode incrementally: `push(observation, action)` per step, `finish()` at episode end."""

    def __init__(self, model: PSModel, min_len: int = 1) -> None:
        model.eval()
        self.model = model
        self.decoder = OnlineDecoder(max_len=model.max_len, min_len=min_len)
        self._scorer = IncrementalEndScorer(model)  # each step's column of end scores
        self._features: list[torch.Tensor] = []  # the last L_max+1+lookahead are needed; older dropped
        self._offset = 0  # step index of self._features[0]
        # The action encoders' inputs for the next observation, from the action pushed with the last one.
        self._next_action_inputs: dict[str, np.ndarray] | None = model.encoders.previous_action_inputs(
            None, "observation 0"
        )

    @property
    def num_observations(self) -> int:
        return self._offset + len(self._features)

    @torch.no_grad()
    def push(self, observation: Mapping[str, np.ndarray], action: np.ndarray | None = None) -> list[Segment]:
        """Add observation o_t (t = 0, 1, ...) and a_t, the action taken after it; returns the segments
        decided by o_t.

        ``observation`` maps feature names (``observation.images.<camera>``, ``observation.state``) to
        one row each; features the model does not read are ignored. ``action`` is what a PlayStep carries
        with o_t; a model that reads actions needs it for every observation but the episode's last (it
        is read with o_{t+1}). ValueError naming the step and feature for a bad observation or action.
        """
        where = f"step {self.num_observations}"
        if self._next_action_inputs is None:
            raise PlaysegError(f"observation {self.num_observations}: the previous step carried no action")
        inputs = {**self.model.encoders.observation_inputs(observation, where), **self._next_action_inputs}
        self._next_action_inputs = None
        if not self.model.reads_actions:
            self._next_action_inputs = {}
        elif action is not None and np.asarray(action).size:
            self._next_action_inputs = self.model.encoders.previous_action_inputs(
                action, f"action of {where}"
            )
        feature = self.model.encode_steps(to_device(as_tensors(inputs), self.model.device))[0]
        self._features.append(feature)
        self._scorer.push(feature)
        if self.num_observations < 2 + self.model.lookahead:
            return []
        return self._label(self.decoder.push(self._end_column()))

    def _end_column(self) -> np.ndarray:
        """The column of ends ``lookahead`` rows before the last pushed (`PSModel.end_column` of the kept
        rows)."""
        return self._scorer.column(self._offset).double().cpu().numpy()

    @torch.no_grad()
    def finish(self) -> list[Segment]:
        """The episode ended with the last pushed frame: decide the remaining segments."""
        if self.decoder.finished:
            raise RuntimeError("StreamingSegmenter.finish called twice: one segmenter per episode")
        if self.num_observations < 2:
            return []
        num_steps = self.num_observations - 1
        if num_steps < self.decoder.min_len:
            return [self._whole_episode(num_steps)]
        # Ends the lookahead has kept waiting: score them reading zero rows past the last observation.
        decided, zero = [], torch.zeros_like(self._features[0])
        for end in range(max(1, self.num_observations - self.model.lookahead), self.num_observations):
            while self._scorer.t < end + self.model.lookahead:  # zero rows up to the end's lookahead
                self._scorer.push(zero)
            decided += self.decoder.push(self._end_column())
        return self._label(decided + self.decoder.finish())

    def _whole_episode(self, num_steps: int) -> Segment:
        """An episode shorter than L_min is one segment, as `segment_episode` cuts it (nothing was
        committed, so every row from o_0 is kept)."""
        features = torch.stack(self._features)
        end_logits = self.model.end_logits(features).double().cpu().numpy()[:, :num_steps]
        log_score = decode_segments(end_logits, min_len=num_steps, max_len=num_steps).log_score
        self.decoder.finished = True
        label_logits = self.model.label_logits(features, 0, num_steps)
        return labelled_segment(self.model, 0, num_steps, label_logits, log_score)

    def _label(self, decided: Sequence[tuple[int, int]]) -> list[Segment]:
        scores = (
            {(c.start, c.end): c.log_score for c in self.decoder.commits[-len(decided) :]} if decided else {}
        )
        segments = []
        for start, end in decided:
            window = torch.stack(self._features[start - self._offset : end + 1 - self._offset])
            # As PSModel.label_logits, on the kept window (its start flag is the episode's, not the window's).
            hidden = self.model.trunk(window[None], torch.tensor([start == 0], device=window.device))
            label_logits = self.model.label_head(hidden[0, -1])
            segments.append(labelled_segment(self.model, start, end, label_logits, scores[(start, end)]))
        if decided:  # steps before the last decided end are never needed again
            keep_from = decided[-1][1] - self._offset
            self._features = self._features[keep_from:]
            self._offset += keep_from
        return segments
