"""PS end scores of a stream, one step at a time, at O(L_max) trunk positions per step.

`PSModel.end_column` scores the ends at step t from scratch: every window that could hold a segment
ending there (up to L_max + 1 + lookahead of them) goes through the trunk over its whole length, which is
O(L_max^2) positions per step. The trunk is causal from each window's start (StartCausalTrunk), so a
window's state at position p follows from its state up to p - 1 and the new step alone: its convolutions
need the last kernel-1 normalised inputs of each layer, its running max the maximum so far. This module
keeps that state for every window start still in reach and advances each by the new step: one position
per start per step. The columns equal `end_column`'s up to float rounding (the same operations, summed in
another order). Periodic embeddings (ps/model.py `PeriodicEmbedding`) read the change since each start,
so the kept starts' rows are kept too.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from playseg_core.ps.model import PSModel


class IncrementalEndScorer:
    """`push(features of o_t)` for t = 0, 1, ... then `column(first_kept)`: what `PSModel.end_column`
    returns for the kept rows first_kept .. t (of at most L_max + 1 + lookahead), computed incrementally.

    The kept starts are always the consecutive steps first_start .. t: each push opens one and drops those
    out of reach; `column` drops the starts before ``first_kept`` (rows the caller dropped after committing
    their segments: their windows are never scored again).
    """

    def __init__(self, model: PSModel) -> None:
        trunk = model.trunk
        self.model = model
        step_dim = model.step_dim
        weight = trunk.in_proj.weight
        own, start, difference = (
            weight[:, :step_dim],
            weight[:, step_dim : 2 * step_dim],
            weight[:, 2 * step_dim :],
        )
        # [o, o_s, o - o_s] @ W = o @ (own + difference) + o_s @ (start - difference): a part of each step,
        # computed once, and a part of each window's start, kept with the start.
        self.step_weight = own + difference
        self.start_weight = start - difference
        self.start_bias = trunk.in_proj.bias
        self.convs = [
            # (out, in, k) -> (out, k * in), matching the k last inputs stacked oldest first
            block.conv.weight.permute(0, 2, 1).reshape(block.conv.weight.shape[0], -1)
            for block in trunk.blocks
        ]
        self.kernel = trunk.blocks[0].conv.kernel_size[0] if trunk.blocks else 1
        self.reach = model.max_len + model.lookahead  # the oldest start a window of the column can have
        hidden = trunk.in_proj.out_features
        device, dtype = weight.device, weight.dtype
        self.t = -1
        self.first_start = 0  # the kept starts are steps first_start .. t
        self._descending = torch.arange(self.reach, -1, -1, device=device)  # positions, oldest start first
        self.start_part = torch.zeros(0, hidden, device=device, dtype=dtype)
        # the kept starts' rows, for the periodic embeddings of the change since the start (not linear)
        self.start_rows = torch.zeros(0, step_dim, device=device, dtype=dtype)
        self.caches = [
            torch.zeros(0, self.kernel - 1, hidden, device=device, dtype=dtype) for _ in trunk.blocks
        ]
        self.maxima = torch.zeros(0, hidden, device=device, dtype=dtype)
        # the trunk's output at each start's last 1 + lookahead positions, oldest first
        self.recent = torch.zeros(0, 1 + model.lookahead, hidden, device=device, dtype=dtype)

    @torch.no_grad()
    def push(self, feature: torch.Tensor) -> None:
        """Advance every kept window by step t's features (step_dim,), and open the window starting at t."""
        trunk = self.model.trunk
        self.t += 1
        self._drop_before(self.t - self.reach)
        new_start = F.linear(feature, self.start_weight, self.start_bias)
        hidden = self.start_part.shape[1]
        self.start_part = torch.cat([self.start_part, new_start[None]])
        if trunk.periodic is not None:
            self.start_rows = torch.cat([self.start_rows, feature[None]])
        self.caches = [torch.cat([c, c.new_zeros(1, self.kernel - 1, hidden)]) for c in self.caches]
        self.maxima = torch.cat([self.maxima, self.maxima.new_full((1, hidden), float("-inf"))])
        self.recent = torch.cat([self.recent, self.recent.new_zeros(1, *self.recent.shape[1:])])

        kept = self.t - self.first_start + 1
        projected = F.linear(feature, self.step_weight)[None] + self.start_part
        if trunk.periodic is not None:
            projected = projected + trunk.periodic(feature[None].expand(kept, -1), self.start_rows)
        h = trunk.in_norm(projected)
        h = h + trunk.offset.weight[self._descending[-kept:]]  # start s is at position t - s
        if self.first_start == 0:  # the window starting the episode is flagged, as in training
            h[0] = h[0] + trunk.episode_start
        for index, block in enumerate(trunk.blocks):
            normed = block.norm(h)
            stacked = torch.cat([self.caches[index], normed[:, None]], dim=1)
            self.caches[index] = stacked[:, 1:]
            conv = F.linear(stacked.reshape(kept, -1), self.convs[index], block.conv.bias)
            h = h + block.out(F.gelu(conv))
        self.maxima = torch.maximum(self.maxima, trunk.memory(trunk.memory_norm(h)))
        out = trunk.norm(h + self.maxima)
        self.recent = torch.cat([self.recent[:, 1:], out[:, None]], dim=1)

    @torch.no_grad()
    def column(self, first_kept: int) -> torch.Tensor:
        """(L_max,) logits: [k] = the segment [e-k-1, e) ends at e = t - lookahead; -inf where its start is
        before ``first_kept`` or out of reach (as `PSModel.end_column` on the kept rows)."""
        model = self.model
        self._drop_before(first_kept)
        end = self.t - model.lookahead
        column = torch.full(
            (model.max_len,), float("-inf"), dtype=self.recent.dtype, device=self.recent.device
        )
        scored = end - self.first_start  # starts first_start .. end - 1
        if scored < 1:
            return column
        read = self.recent[:scored].reshape(scored, -1)  # positions e-s .. e-s+lookahead of each start s
        logits = model.end_head(read).squeeze(-1) + model.end_bias
        column[:scored] = logits.flip(0)  # start s is k = e - s - 1
        return column

    def _drop_before(self, first: int) -> None:
        drop = first - self.first_start
        if drop <= 0:
            return
        self.first_start = first
        self.start_part, self.start_rows = self.start_part[drop:], self.start_rows[drop:]
        self.caches = [cache[drop:] for cache in self.caches]
        self.maxima, self.recent = self.maxima[drop:], self.recent[drop:]
