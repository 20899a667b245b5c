"""Do PS's own cuts of the tabletop's block tasks become trustworthy when the end and the label are scored
together? A probe of a PS model trained with its end grounded on the label (`--end-grounding`).

PS segments the val episodes as it segments play (its end bias, the truth hidden), and each cut is ranked
three ways, a cut being right when its label is the true instruction of most of its steps (as the
own-cut filter counts, `calibrate_on_own_cuts`):

- ``segment``: `segment_probability`, the label's probability times the cut's (the own-cut filter's
  score; the cut's probability marginalised over the label head's guesses);
- ``told``: the label's probability times the cut's probability told that label (the grounded end reads
  what the label names), the joint probability of the (segment, label) pair given its start;
- ``joint``: the same, maximised over the label head's ``--candidates`` likeliest labels (the cut
  relabelled to its best pair).

Prints the share right among the top 5 / 10 / 20 / 40 / 80 cuts and, per family of the label, among
each family's top 5 / 10 / 20:

    .venv/bin/python benchmarks/tabletop_end_grounding.py --data /tmp/ttps/data --out /tmp/ground --grounding 2
    .venv/bin/python benchmarks/tabletop_joint_rank.py --model /tmp/ground/ps-grounding2.pt --data /tmp/ttps/data
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Segment
from playseg_core.domains.tabletop.instructions import task_for
from playseg_core.ps.calibration import majority_instructions, own_cuts
from playseg_core.ps.labelling import segment_probability
from playseg_core.ps.model import PSModel, load_model


@torch.no_grad()
def told_scores(model: PSModel, features: torch.Tensor, cut: Segment, candidates: int) -> dict[int, float]:
    """Label index -> log p(label | cut) + log p(the cut ends exactly at its end | its start, told the
    label), for the cut's own label and the label head's ``candidates`` likeliest."""
    length = cut.end - cut.start
    width = length + 1 + model.lookahead
    window = features.new_zeros(1, width, features.shape[1])
    rows = features[cut.start : cut.start + width]
    window[0, : rows.shape[0]] = rows  # zero padding past the episode, as segmenting reads it
    hidden = model.trunk(window, torch.tensor([cut.start == 0]))
    log_q = torch.log_softmax(model.label_head(hidden[0, length]).double(), dim=-1)
    labels = dict.fromkeys(
        [model.instructions.index(cut.instruction), *log_q.topk(candidates).indices.tolist()]
    )
    scores = {}
    for label in labels:
        told = model.told_end_logits(hidden, window, torch.tensor([label]))[0, 1 : length + 1].double()
        told = told + model.end_bias
        scores[label] = float(log_q[label] + F.logsigmoid(-told[:-1]).sum() + F.logsigmoid(told[-1]))
    return scores


def ranked_rows(model: PSModel, data: PlayDataset, split: str, candidates: int) -> list[dict]:
    rows = []
    for episode, cut in own_cuts(model, data.episodes(split, truth=True)):
        features = model.encode_episode(episode.with_segments([]))
        truth = majority_instructions(cut, episode.segments, episode.num_steps)
        for segment, true in zip(cut, truth, strict=True):
            row = {"segment": (segment_probability(segment), segment.instruction == true)}
            row["family"] = task_for(segment.instruction).family
            if model.grounded_end is not None:
                scores = told_scores(model, features, segment, candidates)
                own = model.instructions.index(segment.instruction)
                best = max(scores, key=scores.__getitem__)
                row["told"] = (math.exp(scores[own]), segment.instruction == true)
                row["joint"] = (math.exp(scores[best]), model.instructions[best] == true)
                row["joint_family"] = task_for(model.instructions[best]).family
            rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--model", required=True, help="a tabletop PS checkpoint (grounded for the told rows)"
    )
    parser.add_argument("--data", required=True, help="the generated dataset it was trained on")
    parser.add_argument("--split", default="val", help="annotated split to cut and rank")
    parser.add_argument("--candidates", type=int, default=8, help="labels the joint row tries per cut")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    try:
        model, _ = load_model(Path(args.model), ("ps",))
        data = PlayDataset.open(args.data)
    except (OSError, ValueError) as error:
        raise SystemExit(f"{error}") from None
    rows = ranked_rows(model, data, args.split, args.candidates)
    print(f"{args.split}: {len(rows)} cuts, {np.mean([r['segment'][1] for r in rows]):.3f} right")
    for score in ("segment", "told", "joint"):
        if score not in rows[0]:
            continue
        order = sorted(rows, key=lambda r: -r[score][0])
        tops = "  ".join(
            f"top {k} {np.mean([r[score][1] for r in order[:k]]):.2f}" for k in (5, 10, 20, 40, 80)
        )
        print(f"{score:8s} {tops}")
        by_family = defaultdict(list)
        for r in order:
            by_family[r["joint_family" if score == "joint" else "family"]].append(r[score][1])
        for family, right in sorted(by_family.items()):
            tops = "  ".join(f"top {k} {np.mean(right[:k]):.2f}" for k in (5, 10, 20) if len(right) >= k)
            print(f"    {family:22s} {len(right):4d} cuts, {np.mean(right):.2f} right  {tops}")


if __name__ == "__main__":
    main()
