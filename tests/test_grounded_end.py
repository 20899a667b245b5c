"""PS's end head grounded on the label (ps/model.py `GroundedEndHead`): it learns to read the thing a
label names, a PS model with it scores ends the same offline, in chunks and live, survives a checkpoint,
and is refused where no encoder tracks things by position."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from test_models import INSTRUCTIONS, tiny_model_config

from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.model import GroundedEndHead, PSModel, load_model, save_model
from playseg_core.ps.segmentation import segment_episode
from playseg_core.ps.streaming import StreamingSegmenter
from playseg_core.ps.training import TrainConfig, model_config_for, train_ps
from playseg_ros.cli import main as cli_main

torch.set_num_threads(1)


def test_the_head_reads_the_thing_the_label_names() -> None:
    """Three things move at random; a segment labelled "watch the <name> thing" ends when that one has
    moved far from where it started. Only the label says which one: the head must attend to it."""
    names = ["red", "green", "blue"]
    labels = [f"watch the {name} thing" for name in names]
    generator = torch.Generator().manual_seed(0)
    head = GroundedEndHead(labels, [(0, 3)], hidden_in=1, heads=1)
    optimizer = torch.optim.Adam(head.parameters(), lr=3e-3)

    def batch(size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        steps = torch.randn(size, 12, 3, 2, generator=generator) * 0.3
        where = steps.cumsum(1)
        where[:, 0] = 0.0  # every thing starts at the origin
        label = torch.randint(3, (size,), generator=generator)
        moved = where[torch.arange(size), :, label].norm(dim=-1)  # (size, 12)
        return where.flatten(2), label[:, None, None].expand(-1, 12, 1), (moved > 1.0).float()

    for _ in range(600):
        windows, label, target = batch(64)
        logits = head(torch.zeros(64, 12, 1), windows, label).squeeze(-1)
        loss = F.binary_cross_entropy_with_logits(logits, target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    windows, label, target = batch(512)
    with torch.no_grad():
        told = head(torch.zeros(512, 12, 1), windows, label).squeeze(-1)
        wrong = head(torch.zeros(512, 12, 1), windows, (label + 1) % 3).squeeze(-1)
    accuracy = ((told > 0).float() == target).float().mean()
    misled = ((wrong > 0).float() == target).float().mean()
    print(f"told the label: {float(accuracy):.3f}, told another: {float(misled):.3f}")
    assert accuracy > 0.9 and misled < accuracy - 0.15, (float(accuracy), float(misled))


@pytest.fixture(scope="module")
def tabletop(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("grounded") / "tiny"
    argv = ["generate", "--domain", "tabletop", "--preset", "tiny", "--out", str(out), "--quiet"]
    assert cli_main(argv) == 0
    return out


@pytest.fixture(scope="module")
def grounded(tabletop: Path) -> PSModel:
    dataset = PlayDataset.open(tabletop)
    train = list(dataset.episodes("train"))
    config = model_config_for(
        dataset.features,
        dataset.domain,
        len(dataset.instructions),
        max_len=40,
        episodes=train,
        end_grounding=2,
    )
    assert config.end_grounding == 2 and config.end_lookahead == 2  # the domain's lookahead, and grounded
    cfg = TrainConfig(epochs=1, segments_per_batch=8, seed=0, domain=dataset.domain)
    result = train_ps(train, list(dataset.episodes("val")), dataset.instructions, cfg, config)
    model = result.model.eval()
    assert model.grounded_end is not None
    with torch.no_grad():  # after one epoch it adds little: make it count in what the tests compare
        model.grounded_end.out.weight.add_(0.05)
    return model


def test_offline_chunked_and_live_scoring_agree(grounded: PSModel, tabletop: Path) -> None:
    episode = next(e for e in PlayDataset.open(tabletop).episodes("test"))
    features = grounded.encode_episode(episode)
    with torch.no_grad():
        whole = grounded.end_logits(features, chunk=episode.num_steps)
        torch.testing.assert_close(grounded.end_logits(features, chunk=7), whole, rtol=1e-4, atol=1e-4)
        lookahead = grounded.lookahead
        padded = torch.cat([features, features.new_zeros(lookahead, features.shape[1])])
        for end in (5, 37, 90, episode.num_steps):
            first = max(0, end - grounded.max_len)
            column = grounded.end_column(padded[first : end + 1 + lookahead], starts_episode=first == 0)
            for k in range(end - first):
                torch.testing.assert_close(column[k], whole[end - k - 1, k], rtol=1e-4, atol=1e-4)
    offline = [(s.start, s.end, s.instruction) for s in segment_episode(grounded, episode)]
    live = StreamingSegmenter(grounded)
    found = []
    for t in range(episode.num_steps + 1):
        observation = {name: frames[t] for name, frames in episode.images.items()}
        if episode.state is not None:
            observation[grounded.cfg.features.state.name] = episode.state[t]
        found += live.push(observation, episode.actions[t] if t < episode.num_steps else None)
    found += live.finish()
    assert len(offline) > 1 and [(s.start, s.end, s.instruction) for s in found] == offline


def test_a_checkpoint_keeps_the_grounded_head(grounded: PSModel, tabletop: Path, tmp_path: Path) -> None:
    path = save_model(tmp_path / "grounded.pt", grounded)
    loaded, _ = load_model(path)
    assert isinstance(loaded, PSModel) and loaded.cfg.end_grounding == 2
    episode = next(e for e in PlayDataset.open(tabletop).episodes("val"))
    with torch.no_grad():
        features = grounded.encode_episode(episode)
        torch.testing.assert_close(loaded.end_logits(features), grounded.end_logits(features))


def test_a_model_without_position_slots_is_refused() -> None:
    config = tiny_model_config(5, 0)
    config.end_grounding = 1
    with pytest.raises(
        ValueError, match="end_grounding: none of the model's step encoders gives things' positions"
    ):
        PSModel(config, INSTRUCTIONS)
