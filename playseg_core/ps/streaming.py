"""Play Segmentation of a stream: one episode fed frame by frame, segments emitted as soon as decided.

Each frame is encoded once; at step t the PS model scores every segment that could end at t (one column
of the end-logit matrix, from the last L_max+1 frame features) and the online decoder commits boundaries
once every surviving best path passes through them. The output equals `segment_episode` on the whole
episode (same model, same decoder recursion and tie rule).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from playseg_core.data.episode import Segment
from playseg_core.ps.decoding import OnlineDecoder
from playseg_core.ps.model import PSModel, previous_actions
from playseg_core.ps.segmentation import labelled_segment


class StreamingSegmenter:
    """Segments one episode incrementally: `push(frame, action)` per step, `finish()` at episode end."""

    def __init__(self, model: PSModel, min_len: int = 1) -> None:
        model.eval()
        self.model = model
        self.decoder = OnlineDecoder(max_len=model.max_len, min_len=min_len)
        self._features: list[torch.Tensor] = []  # only the last L_max+1 are needed; older are dropped
        self._offset = 0  # step index of self._features[0]
        self._segments: list[Segment] = []
        self._pending_action: int | None = None  # a_t of the last pushed o_t: read with o_{t+1}

    @property
    def num_frames(self) -> int:
        return self._offset + len(self._features)

    @torch.no_grad()
    def push(self, frame: np.ndarray, action: np.ndarray | None = None) -> list[Segment]:
        """Add observation o_t (t = 0, 1, ...) and a_t, the action taken after it; returns the segments
        decided by o_t.

        `action` is what a PlayStep carries with o_t; a model that reads actions needs it for every
        observation but the episode's last (it is read with o_{t+1}). A frames-only model ignores it.
        """
        prev = None
        if self.model.reads_actions:
            if self._pending_action is None and self.num_frames > 0:
                raise ValueError(f"observation {self.num_frames}: the previous step carried no action")
            prev = torch.tensor(
                [self.model.cfg.num_actions if self.num_frames == 0 else self._pending_action]
            )
            self._pending_action = None
            if action is not None and np.asarray(action).size:
                where = f"action of step {self.num_frames}"
                self._pending_action = int(
                    previous_actions(
                        np.asarray(action, np.float32).reshape(1, -1), self.model.cfg.num_actions, where
                    )[1]
                )
        feature = self.model.encode_steps(torch.from_numpy(np.array(frame, np.uint8))[None], prev)[0]
        self._features.append(feature)
        if self.num_frames < 2:
            return []
        window = torch.stack(self._features[-(self.model.max_len + 1) :])
        at_episode_start = self.num_frames - len(window) == 0
        column = self.model.end_column(window, at_episode_start).double().numpy()
        return self._label(self.decoder.push(column))

    @torch.no_grad()
    def finish(self) -> list[Segment]:
        """The episode ended with the last pushed frame: decide the remaining segments."""
        if self.num_frames < 2:
            return []
        return self._label(self.decoder.finish())

    def _label(self, decided: Sequence[tuple[int, int]]) -> list[Segment]:
        scores = (
            {(c.start, c.end): c.log_score for c in self.decoder.commits[-len(decided) :]} if decided else {}
        )
        segments = []
        for start, end in decided:
            window = torch.stack(self._features[start - self._offset : end + 1 - self._offset])
            # As PSModel.label_logits, on the kept window (its start flag is the episode's, not the window's).
            hidden = self.model.trunk(window[None], torch.tensor([start == 0]))
            label_logits = self.model.label_head(hidden[0, -1])
            segments.append(labelled_segment(self.model, start, end, label_logits, scores[(start, end)]))
        if decided:  # frames before the last decided start are never needed again
            keep_from = decided[-1][1] - self._offset
            self._features = self._features[keep_from:]
            self._offset += keep_from
        self._segments.extend(segments)
        return segments
