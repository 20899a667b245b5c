"""The policy trainers (the generic ``bc`` policy, BabyAI's FiLM policy) train through the one training
loop (playseg_core/training/loop.py) and, on the CPU, give bit for bit the weights of the loops they had
before: each test here holds a copy of such a loop, a few steps long, to compare with."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_bc_policy import make_clips, robot_features
from torch import nn
from torch.nn import functional as F

import playseg_core.augment.bc_policy as bc_policy
import playseg_core.domains.babyai.imitation as imitation
from playseg_core.augment.bc_policy import BCPolicyLearner, _Steps
from playseg_core.augment.policies import load_policy_learner
from playseg_core.augment.policy import SequentialDraws, torch_threads
from playseg_core.data.features import STATE
from playseg_core.domains.babyai.imitation import (
    PolicyTrainConfig,
    flatten_segments,
    learning_rate_at,
    mirror_samples,
    train_policy,
)
from playseg_core.domains.babyai.policy import AGENT_TYPE, PolicyConfig, PolicyNet
from playseg_core.training.device import DeviceError

SMALL = PolicyConfig(channels=8, cell_embedding=8, word_embedding=8, instruction_dim=16, head_hidden=16)


def reference_bc(learner: BCPolicyLearner, clips) -> tuple[nn.Module, dict[str, float]]:
    """The ``bc`` learner's training as its own loop did it before the training loop (no augment, no
    moved entities): (weights, validation figures)."""
    s = learner.settings
    train_clips, val_clips = learner._split(list(clips))
    names = [*learner.features.cameras, STATE]
    with torch_threads(s.num_threads), torch.random.fork_rng(devices=[]):
        torch.manual_seed(s.seed)
        rng = np.random.default_rng(s.seed)
        model = learner.build(train_clips)
        train_steps = _Steps(train_clips, names, learner.features.action.num_values)
        optimiser = torch.optim.AdamW(model.parameters(), lr=s.lr, weight_decay=s.weight_decay)
        model.train()
        for _ in range(s.steps):
            which = rng.integers(0, len(train_steps), size=s.batch_size)
            drop = rng.random(s.batch_size) < s.instruction_dropout
            loss, _, moved_loss, _ = learner._loss(model, train_steps.batch(which), drop, {})
            optimiser.zero_grad(set_to_none=True)
            (loss + moved_loss).backward()
            nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            optimiser.step()
        val_steps = _Steps(val_clips, names, learner.features.action.num_values)
        figures = learner._validate(model, val_steps, train_steps, None)
    return model, figures


def reference_babyai(segments, config: PolicyTrainConfig) -> nn.Module:
    """BabyAI's imitation training as its own loop did it before the training loop."""
    with torch_threads(config.num_threads):
        return _reference_babyai(segments, config)


def _reference_babyai(segments, config: PolicyTrainConfig) -> nn.Module:
    data = flatten_segments(segments, config.policy.max_words)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    model = PolicyNet(config.policy)
    optimizer = torch.optim.Adam(
        model.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay
    )
    model.train()
    for step in range(1, config.steps + 1):
        segment = rng.integers(0, len(data.lengths), config.batch_size)
        timestep = (rng.random(config.batch_size) * data.lengths[segment]).astype(np.int64)
        rows = torch.from_numpy(data.offsets[segment] + timestep)
        instruction = torch.from_numpy(data.instruction_index[segment])
        states, targets = data.states[rows], data.actions[rows]
        if config.mirror_augmentation:
            mirror = torch.from_numpy(rng.random(config.batch_size) < 0.5)
            states[mirror], targets[mirror] = mirror_samples(states[mirror], targets[mirror])
        logits = model(states, data.word_ids[instruction], data.word_lengths[instruction])
        loss = F.cross_entropy(logits, targets)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate_at(step, config)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        optimizer.step()
    return model.eval()


def demonstrations(num: int, seed: int) -> list:
    """Grid demonstrations of random lengths: an agent somewhere on random cells, random actions."""
    rng = np.random.default_rng(seed)
    words = ("go to the red ball", "go to the blue key", "go to a green box")
    out = []
    for i in range(num):
        length = int(rng.integers(1, 6))
        states = rng.integers(0, 6, size=(length + 1, 8, 8, 3), dtype=np.uint8)
        states[:, 3, 4] = (AGENT_TYPE, 0, rng.integers(0, 4))
        out.append((words[i % 3], states, rng.integers(0, 3, size=length)))
    return out


def assert_same_weights(got: nn.Module, expected: nn.Module) -> None:
    got_state, expected_state = got.state_dict(), expected.state_dict()
    assert got_state.keys() == expected_state.keys()
    differ = [key for key in got_state if not torch.equal(got_state[key], expected_state[key])]
    assert not differ, f"weights differ from the reference loop's: {differ}"


class Spy:
    """Records the calls of a module's `train_loop` and passes them on."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, module) -> None:
        self.calls: list = []
        real = module.train_loop

        def spy(task, cfg):
            self.calls.append((task, cfg))
            self.result = real(task, cfg)
            return self.result

        monkeypatch.setattr(module, "train_loop", spy)


@pytest.mark.parametrize("discrete", [False, True])
def test_bc_trains_through_the_loop_bit_for_bit_as_its_own_loop_did(monkeypatch, discrete: bool) -> None:
    settings = {"steps": 12, "batch_size": 16, "seed": 3, "val_fraction": 0.2, "weight_decay": 0.01}
    learner = load_policy_learner("bc", settings, features=robot_features(discrete))
    clips = make_clips(20, seed=1, discrete=discrete)
    spy = Spy(monkeypatch, bc_policy)
    model, report = learner.train(clips)
    expected, figures = reference_bc(learner, clips)
    assert_same_weights(model, expected)
    assert report.val_loss == figures["val_loss"] and report.baseline_val_loss == figures["baseline_val_loss"]
    assert report.val_accuracy == figures.get("val_accuracy")
    ((task, cfg),) = spy.calls
    assert cfg.steps == 12 and cfg.grad_clip == 1.0 and cfg.patience == 0 and cfg.device.type == "cpu"
    assert task.evaluate is not None and spy.result.stopped == "step cap" and report.steps == 12


def test_bc_honours_its_budget_settings(monkeypatch) -> None:
    features = robot_features()
    clips = make_clips(20, seed=1)
    spy = Spy(monkeypatch, bc_policy)
    timed = load_policy_learner("bc", {"steps": 50, "batch_size": 8, "max_minutes": 1e-9}, features=features)
    _, report = timed.train(clips)
    assert report.steps == 1 and spy.result.stopped == "max minutes"
    assert [step for step, _ in report.losses] == [1] and report.val_loss is not None
    early = {"steps": 40, "batch_size": 8, "eval_every": 2, "patience": 3, "device": "cpu", "log_every": 5}
    _, report = load_policy_learner("bc", early, features=features).train(clips)
    task, cfg = spy.calls[-1]
    assert (cfg.eval_every, cfg.patience, cfg.steps, cfg.device) == (2, 3, 40, torch.device("cpu"))
    assert len(spy.result.history) == report.steps // 2 and report.steps <= 40
    # the report holds the kept weights' held-out figures
    assert report.val_loss == spy.result.best["val_loss"]
    assert report.losses[-1][0] == report.steps
    assert load_policy_learner("bc", {"max_minutes": "none"}, features=features).settings.max_minutes is None
    with pytest.raises(ValueError, match="max_minutes > 0"):
        load_policy_learner("bc", {"max_minutes": 0}, features=features)
    with pytest.raises(ValueError, match="eval_every and patience must be >= 0"):
        load_policy_learner("bc", {"patience": -1}, features=features)
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="no CUDA"):
            load_policy_learner("bc", {"device": "cuda"}, features=features).train(clips)


@pytest.mark.parametrize("mirror", [True, False])
def test_babyai_trains_through_the_loop_bit_for_bit_as_its_own_loop_did(monkeypatch, mirror: bool) -> None:
    segments = demonstrations(30, seed=2)
    config = PolicyTrainConfig(
        steps=10, batch_size=16, warmup_steps=3, seed=4, mirror_augmentation=mirror, weight_decay=1e-4,
        policy=SMALL,
    )  # fmt: skip
    spy = Spy(monkeypatch, imitation)
    model, stats = train_policy(segments, config, progress=False)
    assert_same_weights(model, reference_babyai(segments, config))
    ((task, cfg),) = spy.calls
    assert cfg.steps == 10 and cfg.grad_clip == config.grad_clip and task.evaluate is None
    assert isinstance(task.optimizer(PolicyNet(SMALL)), torch.optim.Adam)
    assert task.learning_rate(0) == learning_rate_at(1, config)
    assert stats.steps == 10 and stats.losses[-1][0] == 10


def test_babyai_honours_max_minutes_and_its_device() -> None:
    segments = demonstrations(10, seed=2)
    config = PolicyTrainConfig(
        steps=50, batch_size=8, log_every=20, max_minutes=1e-9, device="cpu", policy=SMALL
    )
    _, stats = train_policy(segments, config, progress=False)
    assert stats.steps == 1 and [step for step, _ in stats.losses] == [1] and 0 <= stats.final_accuracy <= 1
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="no CUDA"):
            train_policy(segments, PolicyTrainConfig(steps=2, device="cuda", policy=SMALL), progress=False)


def test_sequential_draws_are_a_function_of_the_step() -> None:
    """In order: one generator drawn step after step; asked for a later or an earlier step (a resumed
    run), the very same draws."""

    def draw(rng: np.random.Generator, step: int) -> tuple[int, np.ndarray]:
        return step, rng.integers(0, 1000, size=int(rng.integers(1, 4)))  # data-dependent draws

    def skip(rng: np.random.Generator, step: int) -> None:
        rng.integers(0, 1000, size=int(rng.integers(1, 4)))

    rng = np.random.default_rng(7)
    plain = [draw(rng, step) for step in range(8)]
    for make in (lambda: SequentialDraws(7, draw), lambda: SequentialDraws(7, draw, skip)):
        draws = make()
        for step in (0, 1, 5, 6, 2, 7, 7):
            got = draws(step)
            assert got[0] == step and np.array_equal(got[1], plain[step][1])
