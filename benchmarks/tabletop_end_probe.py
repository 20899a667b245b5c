"""Why PS misses the ends of the tabletop's block tasks: a probe of what an end detector needs to see.

PS finds the ends of the block tasks a third to a half of the time, the arm's about 70 % (docs/tabletop.md
"Play Segmentation on the tabletop"). This asks why, on the annotated segments of a generated dataset (the
train split to learn, the val split to score): a small MLP reads each step of a segment, from the one
after its start to 3 past its end, and says whether the segment ends there. It reads the effector's
state, the blocks' positions, how far each has moved since the segment's start, the 4 last and 2 next
commands and the step's offset from the start; the rows differ in

- where the blocks are: found in the camera frames (the object-map encoder's colour blobs, twins told
  apart by size: what PS's `blocks` pooling reads), or their true positions (each episode replayed from
  its seed; the replayed commands are checked against the recorded ones);
- whether the probe is told the segment's true instruction (its family, block, other block, region and
  direction, one-hot), which PS's end head is not;
- `attend`: the camera's positions, but each block a token of its own (its position and displacement,
  plus a learnt embedding of its slot), and two attention heads whose queries come from the instruction
  pick the blocks the MLP reads: how a generic end head conditioned on a label could find what the label
  names, without being given it.

With the true positions and the instruction, whether a task is done is a function of what the probe reads
(the task oracle's), so what it misses there is what the training segments cannot teach it; what it loses
with the camera's positions is perception. A segment's end is found when the first step the probe calls
an end (probability >= 0.5) is within 2 steps of the true one, as PS's figures count it.

It also prints how far the camera's block positions are from the true ones, after the least-squares
affine map from the table to the image.

    .venv/bin/playseg generate --domain tabletop --preset paper --out /tmp/ttps/data --workers 2 --quiet
    .venv/bin/python benchmarks/tabletop_end_probe.py --data /tmp/ttps/data
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from playseg_core.data.dataset import PlayDataset
from playseg_core.data.episode import Episode
from playseg_core.domains.tabletop.encoder import ObjectMapEncoder
from playseg_core.domains.tabletop.instructions import (
    DIRECTIONS,
    FAMILIES,
    REGION_CELLS,
    Task,
    block_gap,
    distance_to_region,
    region_box,
    task_for,
)
from playseg_core.domains.tabletop.play import PlayConfig, replay_scenes
from playseg_core.domains.tabletop.robot_log import dataset_play_config
from playseg_core.domains.tabletop.sim import Scene
from playseg_core.domains.tabletop.spec import BLOCKS, COLOURS, CUBE_SIDE, SHAPES, TABLE_SIZE

POSITIONS = ("camera", "true", "named", "attend")
NUM_BLOCKS = len(BLOCKS)
PAST, NEXT, AFTER = 4, 2, 3  # commands read before and from a step; steps read past the true end
# the encoder orders blocks colour-major (each colour's SHAPES in turn), spec.BLOCKS shape-major
ENCODER_ORDER = [BLOCKS.index(f"{colour} {shape}") for colour in COLOURS for shape in SHAPES]


@dataclass
class ProbeEpisode:
    episode: Episode
    seen: np.ndarray  # (T+1, 16) block positions found in the frames, image units, encoder order
    true: np.ndarray  # (T+1, 16) true block positions (m), the same order
    scenes: list[Scene]  # (T+1) the replay's


def probe_episodes(dataset: PlayDataset, split: str, config: PlayConfig) -> list[ProbeEpisode]:
    camera = dataset.features.cameras[0]
    encoder = ObjectMapEncoder(dataset.features[camera], {"pooling": "blocks", "twins_by_size": True})
    found = []
    for episode in dataset.episodes(split):
        if not episode.segments:
            continue
        scenes, _ = replay_scenes(config, episode.episode_id, episode.actions)
        with torch.no_grad():
            frames = torch.from_numpy(np.array(episode.images[camera]))  # a copy: the dataset maps read-only
            seen = torch.cat([encoder(chunk) for chunk in frames.split(256)]).numpy()
        true = np.stack([scene.blocks for scene in scenes])[:, ENCODER_ORDER].reshape(len(seen), -1)
        found.append(ProbeEpisode(episode, seen, true, scenes))
    return found


TOLD_DIM = len(FAMILIES) + 2 * len(BLOCKS) + len(REGION_CELLS) + len(DIRECTIONS)


def instruction_one_hot(text: str) -> np.ndarray:
    """The task's family, block, other block, region and direction, one-hot."""
    task = task_for(text)
    parts = [
        [task.family == name for name in FAMILIES],
        [task.block == k for k in range(len(BLOCKS))],
        [task.other == k for k in range(len(BLOCKS))],
        [task.region == name for name in REGION_CELLS],
        [task.direction == name for name in DIRECTIONS],
    ]
    return np.concatenate([np.asarray(part, np.float32) for part in parts])


def named_geometry(task: Task, scene: Scene, start: Scene) -> np.ndarray:
    """The true geometry of what ``task`` names: its block's position and displacement since ``start``,
    the other block relative to it, the region's centre relative to what has to reach it, the
    displacement along the direction, the blocks' gap and the distance to the region (zeros for what
    the task does not name): every quantity the task oracle decides by."""
    zero = np.zeros(2)
    block = scene.blocks[task.block] if task.block >= 0 else zero
    moved = block - start.blocks[task.block] if task.block >= 0 else zero
    other = scene.blocks[task.other] - block if task.other >= 0 else zero
    region = zero
    if task.region:
        x_low, y_low, x_high, y_high = region_box(task.region)
        mover = block if task.block >= 0 else scene.effector
        region = np.array([(x_low + x_high) / 2, (y_low + y_high) / 2]) - mover
    along = float(np.dot(DIRECTIONS[task.direction], moved)) if task.direction else 0.0
    # the oracle's own distances: the two blocks' gap, the mover's distance to the region's box
    gap = block_gap(scene, task.block, task.other) if task.other >= 0 else 0.0
    outside = (
        distance_to_region(block if task.block >= 0 else scene.effector, task.region) if task.region else 0.0
    )
    return np.concatenate([block, moved, other, region, [along, gap, outside]])


@dataclass
class Rows:
    x: np.ndarray  # (rows, features)
    y: np.ndarray  # (rows,) 1 at the segment's true end
    segment: np.ndarray  # (rows,) the segment each row belongs to
    offset: np.ndarray  # (rows,) steps from the segment's start
    ends: np.ndarray  # (segments,) the true end's offset
    families: list[str]  # per segment


def probe_rows(episodes: Sequence[ProbeEpisode], positions: str, told: bool) -> Rows:
    xs, ys, segment_of, offsets, ends, families = [], [], [], [], [], []
    for probe in episodes:
        episode = probe.episode
        blocks = probe.true if positions == "true" else probe.seen  # attend: the camera's
        state = episode.state
        assert state is not None
        actions = np.concatenate([np.zeros((PAST, 2), np.float32), episode.actions, np.zeros((NEXT, 2))])
        for segment in episode.segments:
            start, end = segment.start, segment.end
            told_vector = instruction_one_hot(segment.instruction) if told else np.zeros(0, np.float32)
            task = task_for(segment.instruction)
            for t in range(start + 1, min(end + AFTER, episode.num_steps) + 1):
                if positions == "named":
                    where = named_geometry(task, probe.scenes[t], probe.scenes[start])
                else:
                    where = np.concatenate([blocks[t], blocks[t] - blocks[start]])
                xs.append(
                    np.concatenate(
                        [
                            where,
                            state[t],
                            state[t, :2] - state[start, :2],
                            actions[t : t + PAST + NEXT].ravel(),  # a_{t-4} .. a_{t+1}
                            [(t - start) / 50.0],
                            told_vector,
                        ]
                    )
                )
                ys.append(t == end)
                segment_of.append(len(ends))
                offsets.append(t - start)
            ends.append(end - start)
            families.append(task.family)
    return Rows(
        np.asarray(xs, np.float32),
        np.asarray(ys, np.float32),
        np.asarray(segment_of),
        np.asarray(offsets),
        np.asarray(ends),
        families,
    )


class AttendProbe(nn.Module):
    """Rows whose first 4 x NUM_BLOCKS columns are the blocks' positions and displacements and whose last
    ``told_dim`` the instruction: the instruction's queries attend over the blocks' slots (which block,
    not where it is, decides what is read), and the MLP reads what they pick with the other columns."""

    def __init__(self, in_dim: int, told_dim: int, heads: int = 2, dim: int = 64) -> None:
        super().__init__()
        self.told_dim, self.heads, self.dim = told_dim, heads, dim
        self.slot = nn.Parameter(torch.randn(NUM_BLOCKS, dim) * 0.1)
        self.token = nn.Linear(4, dim)
        self.query = nn.Linear(told_dim, heads * dim)
        rest = in_dim - 4 * NUM_BLOCKS
        self.mlp = nn.Sequential(
            nn.Linear(heads * dim + rest, 256), nn.GELU(), nn.Linear(256, 256), nn.GELU(), nn.Linear(256, 1)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        blocks = x[:, : 4 * NUM_BLOCKS].reshape(len(x), 2, NUM_BLOCKS, 2).permute(0, 2, 1, 3).flatten(2)
        query = self.query(x[:, -self.told_dim :]).view(len(x), self.heads, self.dim)
        weights = torch.softmax(query @ self.slot.T / self.dim**0.5, dim=-1)  # (B, heads, blocks)
        picked = weights @ (self.token(blocks) + self.slot)  # (B, heads, dim)
        return self.mlp(torch.cat([picked.flatten(1), x[:, 4 * NUM_BLOCKS :]], dim=-1))


def train_probe(
    rows: Rows, steps: int, seed: int, attend: bool = False
) -> tuple[nn.Module, np.ndarray, np.ndarray]:
    torch.manual_seed(seed)
    mean, std = rows.x.mean(0), rows.x.std(0) + 1e-6
    x, y = torch.from_numpy((rows.x - mean) / std), torch.from_numpy(rows.y)
    if attend:
        model: nn.Module = AttendProbe(x.shape[1], TOLD_DIM)
    else:
        model = nn.Sequential(
            nn.Linear(x.shape[1], 256), nn.GELU(), nn.Linear(256, 256), nn.GELU(), nn.Linear(256, 1)
        )
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        batch = torch.randint(len(x), (512,), generator=generator)
        loss = nn.functional.binary_cross_entropy_with_logits(model(x[batch]).squeeze(-1), y[batch])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return model.eval(), mean, std


def score(model: nn.Module, mean: np.ndarray, std: np.ndarray, rows: Rows) -> tuple[float, dict[str, float]]:
    """Average precision of the end logits, and per family the share of segments whose end is found."""
    with torch.no_grad():
        logits = model(torch.from_numpy((rows.x - mean) / std)).squeeze(-1).numpy()
    order = np.argsort(-logits, kind="stable")
    hits = rows.y[order]
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    average_precision = float((precision * hits).sum() / hits.sum())
    found: dict[str, list[bool]] = {}
    for index, family in enumerate(rows.families):
        mine = rows.segment == index
        called = rows.offset[mine][logits[mine] >= 0.0]
        first = int(called[0]) if len(called) else None
        found.setdefault(family, []).append(first is not None and abs(first - int(rows.ends[index])) <= 2)
    return average_precision, {family: float(np.mean(hit)) for family, hit in sorted(found.items())}


def perception_error(episodes: Sequence[ProbeEpisode]) -> str:
    """How far the blocks found in the frames are from the true ones, in metres on the table."""
    seen = np.concatenate([p.seen for p in episodes]).reshape(-1, 2)
    true = np.concatenate([p.true for p in episodes]).reshape(-1, 2)
    design = np.concatenate([true, np.ones((len(true), 1))], axis=1)
    affine, *_ = np.linalg.lstsq(design, seen, rcond=None)  # table (m) -> image units
    to_table = np.linalg.inv(affine[:2])
    error = np.linalg.norm((seen - affine[2]) @ to_table - true, axis=1)
    far = float(np.mean(error > CUBE_SIDE))
    return (
        f"{len(error):,} block positions: error median {1000 * np.median(error):.1f} mm, 95th percentile "
        f"{1000 * np.quantile(error, 0.95):.1f} mm, over one cube side ({1000 * CUBE_SIDE:.0f} mm) "
        f"{far:.1%}; the table is {1000 * TABLE_SIZE:.0f} mm"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="a generated tabletop dataset")
    parser.add_argument("--steps", type=int, default=4000, help="optimizer steps per probe (512 rows)")
    parser.add_argument("--seeds", type=int, default=3, help="probes trained per row (mean, spread)")
    parser.add_argument(
        "--rows",
        default="camera,camera+told,true,true+told,named+told",
        help="the rows: where the blocks are (camera, true, named: the geometry of what the instruction names, "
        "attend: the camera's, read through the instruction's attention over the blocks), +told: the probe "
        "is told the instruction",
    )
    args = parser.parse_args()
    rows = [(row.removesuffix("+told"), row.endswith("+told")) for row in args.rows.split(",")]
    for positions, told in rows:
        if positions not in POSITIONS or (positions in ("named", "attend") and not told):
            raise SystemExit(
                f"--rows: {args.rows!r}: each is camera, true, named or attend, +told (named and attend "
                "only +told)"
            )
    torch.set_num_threads(2)
    began = time.perf_counter()
    try:  # no dataset, not generated tabletop play, or a replay other than the recording: one line
        dataset = PlayDataset.open(args.data)
        config = dataset_play_config(dataset)
        train, val = (probe_episodes(dataset, split, config) for split in ("train", "val"))
    except (OSError, ValueError) as error:
        raise SystemExit(str(error)) from None
    print(
        f"{args.data}: {sum(len(p.episode.segments) for p in train)} train and "
        f"{sum(len(p.episode.segments) for p in val)} val segments replayed in {time.perf_counter() - began:.0f} s"
    )
    print("the camera's block positions against the true ones:", perception_error(train + val))
    header = None
    for positions, told in rows:
        train_rows, val_rows = probe_rows(train, positions, told), probe_rows(val, positions, told)
        results = []
        for seed in range(args.seeds):
            model, mean, std = train_probe(train_rows, args.steps, seed, attend=positions == "attend")
            results.append(score(model, mean, std, val_rows))
        families = list(results[0][1])
        if header is None:
            header = "| block positions | told the instruction | val AP | " + " | ".join(families) + " |"
            print(f"\nval ends found within 2 steps, mean (min-max) over {args.seeds} probes")
            print(header)
            print("|---" * (3 + len(families)) + "|")
        ap = np.array([r[0] for r in results])
        cells = []
        for family in families:
            shares = np.array([r[1][family] for r in results])
            cells.append(f"{shares.mean():.2f} ({shares.min():.2f}-{shares.max():.2f})")
        print(
            f"| {positions} | {'yes' if told else 'no'} | {ap.mean():.3f} | " + " | ".join(cells) + " |",
            flush=True,
        )


if __name__ == "__main__":
    main()
