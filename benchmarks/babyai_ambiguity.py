"""How much of BabyAI play segmentation is decidable at all: prints the figures behind docs/segmentation.md
"What the data allows".

Usage:
    .venv/bin/python benchmarks/babyai_ambiguity.py --data data/ps10k [--split test] [--pred runs/ps10k-test]

A "go to X" task ends the moment the agent faces an X. Mid-task the agent also faces other objects
(passing by, turning); those moments look like ends. From the symbolic states this script counts:
- true ends vs "decoys": steps inside a segment where the agent faces an object other than the one it
  faced at the segment start (a segment never ends on its start object: consecutive goals differ);
- how many decoys lie on a shortest path to the decoy object too (then "go to <decoy>" followed by the
  rest would have produced the same steps: the play itself is ambiguous there);
- the boundary precision / recall of two reference rules that know each true segment start: cut at
  every decoy and end (what a frame-only end detector does), and the Bayes rule over (steps since
  the start, the last two actions), fitted on the same split (optimistic: an upper-bound estimate).
With --pred (the output of `playseg segment` on that split) it also counts the predicted segments whose
instruction is completed at their end (the agent faces an object of the predicted colour and type that
it did not face at the start): a cut at a decoy with the decoy's label is a valid demonstration even
though exact-match precision counts it wrong.
"""

from __future__ import annotations

import argparse
from collections import Counter, deque

import numpy as np

from playseg_core.data.dataset import PlayDataset

# minigrid: object type ids of box, ball, key; directions 0..3 as (dx, dy); cells an agent can enter.
OBJECT_IDS = (5, 6, 7)
DIRECTION = {0: (1, 0), 1: (0, 1), 2: (-1, 0), 3: (0, -1)}
WALKABLE = (1, 3, 10)  # empty, floor, agent
AGENT = 10


def agent_pose(state: np.ndarray) -> tuple[int, int, int]:
    x, y = np.argwhere(state[:, :, 0] == AGENT)[0]
    return int(x), int(y), int(state[x, y, 2])


def faced_object(state: np.ndarray) -> tuple[int, int] | None:
    """(type id, colour id) of the object in front of the agent, or None."""
    x, y, direction = agent_pose(state)
    dx, dy = DIRECTION[direction]
    cell = state[x + dx, y + dy]
    return (int(cell[0]), int(cell[1])) if cell[0] in OBJECT_IDS else None


def steps_to_face(state: np.ndarray, target: tuple[int, int]) -> int | None:
    """Fewest left/right/forward actions from `state` until the agent faces an object `target`."""
    start = agent_pose(state)
    dist = {start: 0}
    queue = deque([start])
    while queue:
        x, y, direction = pose = queue.popleft()
        dx, dy = DIRECTION[direction]
        ahead = state[x + dx, y + dy]
        if ahead[0] in OBJECT_IDS and (int(ahead[0]), int(ahead[1])) == target:
            return dist[pose]
        moves = [(x, y, (direction + 3) % 4), (x, y, (direction + 1) % 4)]
        if ahead[0] in WALKABLE:
            moves.append((x + dx, y + dy, direction))
        for move in moves:
            if move not in dist:
                dist[move] = dist[pose] + 1
                queue.append(move)
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--data", required=True, help="dataset with states and ground truth")
    parser.add_argument("--split", default="test")
    parser.add_argument("--pred", help="`playseg segment` output for that split: count valid segments")
    args = parser.parse_args()
    dataset = PlayDataset.open(args.data)
    if dataset.features.state is None:
        raise SystemExit(f"{args.data}: the dataset has no states; this analysis needs them")

    ends = decoys = decoys_on_shortest_path = 0
    cells: Counter[tuple[tuple[int, int, int], bool]] = Counter()
    for index in dataset.episode_indices(args.split):
        episode = dataset.episode(index, truth=True)
        states = np.asarray(episode.state)
        actions = np.asarray(episode.actions)[:, 0].astype(int)
        for segment in episode.segments:
            start_object = faced_object(states[segment.start])
            for t in range(segment.start + 1, segment.end + 1):
                faced = faced_object(states[t])
                if faced is None or faced == start_object:
                    continue
                is_end = t == segment.end
                ends += is_end
                if not is_end:
                    decoys += 1
                    decoys_on_shortest_path += (
                        steps_to_face(states[segment.start], faced) == t - segment.start
                    )
                before = actions[t - 2] if t - 2 >= segment.start else -1
                cells[((min(t - segment.start, 10), int(actions[t - 1]), int(before)), is_end)] += 1

    def scores(tp: int, fp: int) -> str:
        precision, recall = tp / (tp + fp), tp / ends
        return f"precision {precision:.3f} recall {recall:.3f} F1 {2 * precision * recall / (precision + recall):.3f}"

    keys = {key for key, _ in cells}
    chosen = [key for key in keys if cells[(key, True)] > cells[(key, False)]]
    print(f"{args.data} split {args.split}: {ends} true ends (the agent faces the goal)")
    print(
        f"decoys (facing another object mid-task): {decoys}; on a shortest path to it too: {decoys_on_shortest_path}"
    )
    print(f"cut at every decoy and end:                 {scores(ends, decoys)}")
    tp = sum(cells[(key, True)] for key in chosen)
    fp = sum(cells[(key, False)] for key in chosen)
    print(f"Bayes rule on (offset, last two actions):   {scores(tp, fp)}")
    if args.pred:
        valid, shortest, total = count_completed_instructions(
            dataset, args.split, PlayDataset.open(args.pred)
        )
        print(
            f"{args.pred}: {total} predicted segments; {valid} ({valid / total:.3f}) complete their instruction,"
        )
        print(
            f"  {shortest} ({shortest / total:.3f}) on a shortest path to it (as good as a bot demonstration)"
        )


def count_completed_instructions(truth: PlayDataset, split: str, pred: PlayDataset) -> tuple[int, int, int]:
    """(predicted segments whose instruction is completed at their end, those of them that take a
    shortest path to it, predicted segments)."""
    from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX

    states = {}
    for index in truth.episode_indices(split):
        episode = truth.episode(index, truth=True)
        states[episode.episode_id] = np.asarray(episode.state)
    valid = shortest = total = 0
    for split_name in pred.splits:
        for episode in pred.episodes(split_name, truth=True):
            episode_states = states[episode.episode_id]
            for segment in episode.segments:
                *_, colour, obj_type = segment.instruction.split()
                goal = (OBJECT_TO_IDX[obj_type], COLOR_TO_IDX[colour])
                faced = faced_object(episode_states[segment.end])
                total += 1
                if faced == goal and faced != faced_object(episode_states[segment.start]):
                    valid += 1
                    shortest += (
                        steps_to_face(episode_states[segment.start], goal) == segment.end - segment.start
                    )
    return valid, shortest, total


if __name__ == "__main__":
    main()
