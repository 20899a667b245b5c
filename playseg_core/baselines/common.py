"""What every segmentation method shares: the training inputs and options, the `Segmenter` interface,
windows of step features, how the window models train through the one loop (training/loop.py), and
per-episode randomness.

A segmenter turns one episode into sorted, disjoint labelled `Segment`s, as PS does, so the same writer,
bags and metrics (ps/metrics.py) serve every method. ``tiles`` says whether its segments cover the whole
trajectory (PS, random windows, changepoints) or are single segments cropped out of windows (UnLoc,
TriDet): for the latter only precision and label accuracy mean anything (the paper reports no recall).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from playseg_core.data.episode import Episode, Segment
from playseg_core.data.features import Features
from playseg_core.errors import PlaysegError
from playseg_core.ps.calibration import LABEL_ACCURACY_TARGET, check_target_accuracy
from playseg_core.ps.encoders import EncoderSpec, StepEncoders, as_tensors
from playseg_core.ps.fixed_features import FixedFeatureCache
from playseg_core.ps.labelling import KeepRule
from playseg_core.ps.metrics import LabelCounts, label_accuracy
from playseg_core.training.device import resolve_device, to_device
from playseg_core.training.loop import LoopConfig, LoopResult, TrainingTask, log_to_stderr, train_loop


@dataclass
class TrainingData:
    """The annotated episodes a method learns from, and how the data is read.

    features: the features to build step encoders for (the action possibly re-declared, see
        `playseg train --actions`); read_actions False leaves the previous action unread.
    augment: each training segment under a random symmetry of the domain's world (its
        ``clip_symmetries``), else with its camera frames rotated/mirrored (only for models that read no
        actions, and only where labels and ends do not depend on orientation); PS and the labelling model.
    bounds: command-line overrides of min_len / max_len / k_max (None: derived, ps.training.segment_bounds).
    """

    train: list[Episode]
    val: list[Episode]
    instructions: list[str]
    features: Features
    domain: str | None = None
    read_actions: bool = True
    encoder_overrides: dict[str, str] = field(default_factory=dict)
    bounds: dict[str, int | None] = field(default_factory=dict)
    # A trained PS or labelling checkpoint whose step encoders the window methods read, frozen (the
    # paper gives TriDet the labelling model's features and UnLoc frozen CLIP features). None: their own,
    # trained with them.
    encoders_from: str | None = None
    augment: bool = False

    def annotated(self) -> list[Episode]:
        episodes = [episode for episode in self.train if episode.segments]
        if not episodes:
            raise PlaysegError("no annotated training episodes (episodes with segments)")
        return episodes


@dataclass
class TrainOptions:
    """Budget, optimiser and device of a training run, for every method (all train through
    playseg_core/training/loop.py).

    The budget: at most ``max_steps`` optimizer steps (None: the method's cap), ended earlier when the
    held-out measure (the val loss) has not improved for ``patience`` evaluations, one every
    ``eval_every`` steps (None: the method's defaults; patience 0: never early), or after
    ``max_minutes``; the weights of the best evaluation are kept. ``epochs``: that many passes over the
    annotated segments instead, without early stopping (``max_steps`` still caps them). Unset options
    keep the method's defaults."""

    seed: int = 0
    max_steps: int | None = None
    epochs: int | None = None
    max_minutes: float | None = None
    patience: int | None = None
    eval_every: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    device: str = "auto"  # training/device.py: auto, cpu, cuda, cuda:N
    num_threads: int | None = None  # torch threads while training (None: as set)
    log: bool = False  # one line per evaluation on stderr
    progress: bool = False  # a progress bar (step / cap, loss, val loss, ETA) on stderr
    state_path: str | None = None  # the loop's resume file (training/loop.py), written every evaluation
    resume: bool = False  # continue from ``state_path``
    fingerprint: str = ""  # what the run is: a resume file of another run is refused
    # the held-out label accuracy a calibrated confidence threshold is chosen for (methods that calibrate)
    label_accuracy: float = LABEL_ACCURACY_TARGET

    def __post_init__(self) -> None:
        check_target_accuracy(self.label_accuracy, "label accuracy target")
        for name in ("max_steps", "epochs", "eval_every", "batch_size"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise PlaysegError(f"{name} must be at least 1, got {value}")
        if self.patience is not None and self.patience < 0:
            raise PlaysegError(f"patience must be 0 (never stop early) or more, got {self.patience}")
        if self.max_minutes is not None and not (self.max_minutes > 0 and math.isfinite(self.max_minutes)):
            raise PlaysegError(f"max_minutes must be a positive number, got {self.max_minutes}")
        if self.lr is not None and not (self.lr > 0 and math.isfinite(self.lr)):
            raise PlaysegError(f"lr must be a positive number, got {self.lr}")

    def step_cap(self, num_segments: int, batch_size: int, default_steps: int) -> int:
        """The most optimizer steps: ``max_steps``, else ``epochs`` passes over ``num_segments`` in
        batches of ``batch_size``, else the method's ``default_steps``."""
        if self.max_steps is not None:
            return self.max_steps
        if self.epochs is not None:
            return max(1, self.epochs * math.ceil(num_segments / batch_size))
        return default_steps

    def patience_or(self, default: int) -> int:
        """Evaluations without improvement that end a run: none with ``epochs`` (a fixed budget), else
        ``patience``, else the method's ``default``."""
        if self.epochs is not None:
            return 0
        return default if self.patience is None else self.patience


@dataclass
class SegmentOptions:
    """Segmentation-time settings: the shortest segment kept (None: the checkpoint's), the seed of
    the random windows (each episode draws from its own stream, so results do not depend on order) and
    the device the window models run on (training/device.py; the other methods run on the CPU)."""

    min_len: int | None = None
    seed: int = 0
    device: str = "cpu"


class Segmenter:
    """A trained segmentation method. Subclasses set the attributes and implement `segment`."""

    method: str = ""
    tiles: bool = True
    instructions: list[str]
    features: Features  # what the model reads, as its training data declared it
    feature_names: list[str]  # the features it actually reads
    # The checkpoint's meta, whose calibration records (PS: "calibration", "own_cuts_calibration") the
    # keep rules' thresholds come from; none: keep by label at threshold 0 (all).
    checkpoint_meta: Mapping[str, Any] = MappingProxyType({})
    source: str = "the checkpoint"  # its path, for errors

    def keep_rule(self, kind: str) -> KeepRule:
        """Which of its segments to use (ps/labelling.py `KEEP_RULES`), with this checkpoint's threshold;
        ValueError naming the checkpoint when it has no calibration for ``kind``."""
        return KeepRule.of_checkpoint(kind, self.checkpoint_meta, self.source)

    @property
    def label_threshold(self) -> float:
        """The label confidence a segment needs to be used (the paper's filter; 0 when uncalibrated)."""
        return self.keep_rule("label").threshold

    def check_features(self, data: Features, what: str) -> None:
        """FeatureError naming the first feature the method reads that ``data`` lacks or declares otherwise."""
        self.features.check_compatible(data, self.feature_names, what)

    def segment(self, episode: Episode) -> list[Segment]:
        raise NotImplementedError


@dataclass
class TrainedSegmenter:
    """The result of training a method: ``save`` writes its checkpoint, ``report`` is a one-line summary."""

    segmenter: Segmenter
    save: Callable[[Path, dict[str, Any]], Path]
    seconds: float
    report: str


def ps_training_setup(data: TrainingData, options: TrainOptions) -> tuple[list[Episode], Any, Any]:
    """(annotated training episodes, TrainConfig, ModelConfig) for training a PS or labelling model on
    ``data`` as `playseg train` would (ps/training.py defaults: the data-scaled budget with early
    stopping), with the options' budget, optimiser and device where given."""
    from dataclasses import replace

    from playseg_core.ps.training import TrainConfig, model_config_for, segment_bounds

    train_eps = data.annotated()
    bounds = segment_bounds(train_eps, data.domain, **data.bounds)
    threads = options.num_threads or torch.get_num_threads()
    cfg = TrainConfig(seed=options.seed, k_max=bounds.k_max, num_threads=threads, device=options.device)
    cfg = replace(cfg, progress=options.progress, log_epochs=options.log)
    cfg = replace(cfg, augment=data.augment, domain=data.domain)
    given = {
        "epochs": options.epochs,
        "max_steps": options.max_steps,
        "max_minutes": options.max_minutes,
        "patience": options.patience,
        "eval_every": options.eval_every,
        "segments_per_batch": options.batch_size,
        "lr": options.lr,
    }
    cfg = replace(cfg, **{key: value for key, value in given.items() if value is not None})
    model_cfg = model_config_for(
        data.features,
        data.domain,
        len(data.instructions),
        max_len=bounds.max_len,
        read_actions=data.read_actions,
        episodes=train_eps,
        overrides=data.encoder_overrides,
        min_len=bounds.min_len,
    )
    return train_eps, cfg, model_cfg


def episode_rng(seed: int, episode_id: str) -> np.random.Generator:
    """Randomness of one episode's windows: depends on the seed and the episode, not on the order."""
    return np.random.default_rng([seed, zlib.crc32(episode_id.encode())])


def annotated_lengths(episodes: Iterable[Episode]) -> np.ndarray:
    lengths = np.array([seg.length for episode in episodes for seg in episode.segments], np.int64)
    if lengths.size == 0:
        raise PlaysegError("the training episodes have no annotated segments")
    return lengths


# ----------------------------------------------------------------------------------------------------
# Step features of windows


def module_device(module: nn.Module) -> torch.device:
    """The device ``module``'s weights are on (the CPU for one without any)."""
    for tensor in (*module.parameters(), *module.buffers()):
        return tensor.device
    return torch.device("cpu")


@torch.no_grad()
def encode_episode(encoders: StepEncoders, episode: Episode, chunk: int = 512) -> torch.Tensor:
    """(T+1, step_dim) step features of every observation row of ``episode``, on the encoders' device."""
    inputs = encoders.episode_inputs(episode)
    rows = episode.num_steps + 1
    device = module_device(encoders)
    return torch.cat(
        [encoders(to_device(as_tensors(inputs, slice(c, c + chunk)), device)) for c in range(0, rows, chunk)]
    )


def window_rows(
    features: torch.Tensor, windows: Sequence[tuple[int, int]]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows o_start..o_end of each step window [start, end) -> (B, P, d) right-padded with zeros, and
    (B, P-1) True at the steps inside the window (P = 1 + the longest window); on ``features``' device."""
    width = max(end - start for start, end in windows) + 1
    batch = features.new_zeros(len(windows), width, features.shape[1])
    valid = torch.zeros(len(windows), width - 1, dtype=torch.bool, device=features.device)
    for row, (start, end) in enumerate(windows):
        batch[row, : end - start + 1] = features[start : end + 1]
        valid[row, : end - start] = True
    return batch, valid


class WindowInputs(NamedTuple):
    """A training batch's windows [start, end) of several episodes, rows o_start..o_end each, right-padded
    to the longest by repeating the last row (any valid row works: padded steps are masked), flattened to
    (B * P, ...) by feature: ``inputs``, the input rows of the encoders that learn; ``encoded``, the output
    rows of those that learn nothing, from a `FixedFeatureCache`; ``valid`` (B, P-1), True at the steps
    inside each window."""

    inputs: dict[str, torch.Tensor]
    encoded: dict[str, torch.Tensor]
    valid: torch.Tensor


def window_inputs(
    encoders: StepEncoders, items: Sequence[tuple[Episode, int, int]], fixed: FixedFeatureCache | None = None
) -> WindowInputs:
    """The `WindowInputs` of windows (episode, start, end): CPU tensors, made without the model's
    gradients (`encode_windows` encodes them). With ``fixed``, the features it caches come as their
    encoder's output rows, each episode encoded once for the whole training: a window model reads every
    annotated step in many batches, and a camera read by an encoder that learns nothing would otherwise be
    encoded again in every one of them."""
    width = max(end - start for _, start, end in items) + 1
    cached = fixed.features if fixed is not None else []
    raw = [spec.feature for spec in encoders.specs if spec.feature not in cached]
    inputs: dict[str, list[np.ndarray]] = {feature: [] for feature in raw}
    encoded: dict[str, list[torch.Tensor]] = {feature: [] for feature in cached}
    valid = torch.zeros(len(items), width - 1, dtype=torch.bool)
    for row, (episode, start, end) in enumerate(items):
        pad = width - (end - start + 1)
        for name, array in encoders.episode_inputs(episode).items():
            if name in cached:
                continue
            clip = np.array(array[start : end + 1])
            inputs[name].append(np.concatenate([clip, np.repeat(clip[-1:], pad, axis=0)]))
        if fixed is not None:
            for name, rows in fixed.clip_rows(episode, start, end).items():
                encoded[name].append(torch.cat([rows, rows[-1:].expand(pad, -1)]))
        valid[row, : end - start] = True
    return WindowInputs(
        {name: torch.from_numpy(np.concatenate(parts)) for name, parts in inputs.items()},
        {name: torch.cat(parts) for name, parts in encoded.items()},
        valid,
    )


def encode_windows(encoders: StepEncoders, windows: WindowInputs) -> torch.Tensor:
    """`window_inputs` encoded with gradients (training) -> (B, P, d) rows, zero past each window."""
    count, width = windows.valid.shape[0], windows.valid.shape[1] + 1
    features = encoders(windows.inputs, windows.encoded).reshape(count, width, -1)
    inside = torch.cat(
        [torch.ones(count, 1, dtype=torch.bool, device=windows.valid.device), windows.valid], 1
    )
    return features * inside[..., None]


def transition_tokens(rows: torch.Tensor) -> torch.Tensor:
    """(B, P, d) observation rows -> (B, P-1, 2d): step t is the transition o_t -> o_{t+1}, which holds
    a_t (read by row t+1's action encoder) and its effect; a segment [s, e) is steps s..e-1."""
    return torch.cat([rows[:, :-1], rows[:, 1:]], dim=-1)


def fixed_windows(num_steps: int, width: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Back-to-back windows of ``width`` steps from a random offset in [0, width): disjoint, so the one
    segment cut from each window never overlaps another's. An episode shorter than ``width`` is one
    window."""
    if num_steps <= width:
        return [(0, num_steps)] if num_steps else []
    offset = int(rng.integers(0, min(width, num_steps - width + 1)))
    return [(start, start + width) for start in range(offset, num_steps - width + 1, width)]


# ----------------------------------------------------------------------------------------------------
# Metrics of segmenters whose segments do not cover the trajectory


def covered_label_accuracy(pred: Sequence[Segment], truth: Sequence[Segment], num_steps: int) -> LabelCounts:
    """Label accuracy over the steps the predicted segments cover (ps.metrics.label_accuracy counts the
    steps no prediction covers as wrong, which says more about coverage than labels for a segmenter that
    leaves steps uncovered)."""
    covered = np.zeros(num_steps, bool)
    for seg in pred:
        covered[seg.start : seg.end] = True
    pieces = []
    for seg in truth:
        inside = np.flatnonzero(covered[seg.start : seg.end]) + seg.start
        # Runs of covered steps inside the true segment, each a piece of the truth with its label.
        for run in np.split(inside, np.flatnonzero(np.diff(inside) > 1) + 1):
            if run.size:
                pieces.append(Segment(int(run[0]), int(run[-1]) + 1, seg.instruction))
    return label_accuracy(pred, pieces, num_steps)


# ----------------------------------------------------------------------------------------------------
# Training of the window models (UnLoc, TriDet) through the one loop (training/loop.py)

WINDOW_STEP_CAP = 2000
"""The window models' default step cap (optimizer steps of 32 windows); early stopping ends most runs
well before it."""
WINDOW_EVAL_EVERY = 25
"""Steps between the held-out evaluations of a window model (each is `VAL_BATCHES` forward passes)."""
WINDOW_PATIENCE = 4
"""Evaluations without a better val loss that end a window model's run."""
VAL_BATCHES = 4
"""Fixed val batches (of the training batch size) whose mean loss is the held-out measure."""
VAL_SEED = 12345


@dataclass
class WindowBatches:
    """How a window model learns: ``choose(rng, training)`` draws one batch's windows (all of its
    randomness; from the training pool, or with ``training`` False from the val pool), ``build(windows)``
    makes their tensors on the CPU (batches can be made ahead, on another thread; the only model part it
    may run is the encoders that learn nothing, once per episode, through a `FixedFeatureCache`), and
    ``loss(model, batch)`` is the batch's loss (the batch on the model's device)."""

    choose: Callable[[np.random.Generator, bool], Any]
    build: Callable[[Any], Any]
    loss: Callable[[nn.Module, Any], torch.Tensor]


class _DrawnBatches:
    """``batch_at(step)`` of the loop: the step-th draw of one stream, ``np.random.default_rng(seed)``,
    so a function of the step alone (what a resumed run and batches made ahead need), and the same
    batches as a loop drawing from that stream step after step. The loop asks the steps in order; an
    earlier step restarts the stream, a later one draws the windows of the steps between (not their
    tensors)."""

    def __init__(self, seed: int, batches: WindowBatches) -> None:
        self.seed, self.batches = seed, batches
        self._restart()

    def _restart(self) -> None:
        self.rng, self.next = np.random.default_rng(self.seed), 0

    def __call__(self, step: int) -> Any:
        if step < self.next:
            self._restart()
        while self.next < step:
            self.batches.choose(self.rng, True)
            self.next += 1
        windows = self.batches.choose(self.rng, True)
        self.next += 1
        return self.batches.build(windows)


def window_learning_rate(step: int, peak: float, steps: int) -> float:
    """The window models' schedule: a linear warm-up over the first 5% of ``steps`` (at least one), then
    a cosine to zero at ``steps``, as they always trained (a LambdaLR of this factor: the loop's
    `cosine_learning_rate` rounds the warm-up and the products differently, in the last bits)."""
    warmup = max(1, steps // 20)
    if step < warmup:
        factor = (step + 1) / warmup
    else:
        factor = 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, steps - warmup)))
    return peak * factor


@dataclass
class FitReport:
    """A window model's run: the loop's result (steps, why it stopped, the kept evaluation, history)."""

    loop: LoopResult

    @property
    def steps(self) -> int:
        return self.loop.steps

    @property
    def seconds(self) -> float:
        return self.loop.seconds

    @property
    def kept(self) -> dict[str, float]:
        """The evaluation whose weights were kept (the last one when none was better)."""
        return self.loop.best or (self.loop.history[-1] if self.loop.history else {})

    @property
    def val_loss(self) -> float | None:
        return self.kept.get("val_loss")

    @property
    def train_loss(self) -> float | None:
        """Mean training loss of the steps before the kept evaluation (since the one before it)."""
        return self.kept.get("train_loss")

    def meta(self) -> dict[str, Any]:
        """What a checkpoint records of the run."""
        return {
            "steps": self.steps,
            "step_cap": self.loop.cap,
            "stopped": self.loop.stopped,
            "best_step": self.loop.best_step,
            "fit_seconds": self.seconds,
            "train_loss": self.train_loss,
            "val_loss": self.val_loss,
            "history": self.loop.history,
        }

    def summary(self) -> str:
        """Steps against the cap, why it stopped, the kept step and its val loss, seconds."""
        return self.loop.summary()


def fit(
    model: nn.Module,
    batches: WindowBatches,
    options: TrainOptions,
    steps: int,
    lr: float,
    name: str,
    val_batches: int = VAL_BATCHES,
    eval_every: int = WINDOW_EVAL_EVERY,
    patience: int = WINDOW_PATIENCE,
) -> FitReport:
    """Train a window model through the loop (training/loop.py): AdamW with warm-up and cosine decay
    over ``steps`` (the cap: `window_learning_rate`), gradients clipped at 5; step s's batch is the s-th
    draw from ``options.seed`` (`_DrawnBatches`); every ``options.eval_every`` (else ``eval_every``)
    steps the mean loss of ``val_batches`` fixed val batches decides the best weights, which are kept,
    and early stopping after ``options``' patience (else ``patience``; none with ``options.epochs``);
    ``options.max_minutes`` ends it too. On ``options.device`` (bf16 autocast on CUDA); the model comes
    back on the CPU, in eval mode."""
    if options.num_threads:
        torch.set_num_threads(options.num_threads)
    device = resolve_device(options.device)
    val_rng = np.random.default_rng(VAL_SEED)  # the same val batches every run and every evaluation
    held_out = [to_device(batches.build(batches.choose(val_rng, False)), device) for _ in range(val_batches)]

    def evaluate(trained: nn.Module) -> dict[str, float]:
        return {"val_loss": float(np.mean([float(batches.loss(trained, batch)) for batch in held_out]))}

    def loss(trained: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, float]]:
        value = batches.loss(trained, batch)
        return value, {"loss": float(value.detach())}

    task = TrainingTask(
        name=name,
        model=model,
        batch_at=_DrawnBatches(options.seed, batches),
        loss=loss,
        learning_rate=lambda step: window_learning_rate(step, lr, steps),
        optimizer=lambda m: torch.optim.AdamW(m.parameters(), lr=lr, weight_decay=1e-4),
        evaluate=evaluate if held_out else None,
    )
    loop_cfg = LoopConfig(
        steps=steps,
        eval_every=options.eval_every or eval_every,
        patience=options.patience_or(patience) if held_out else 0,
        max_minutes=options.max_minutes,
        grad_clip=5.0,
        device=device,
        progress=options.progress,
        log=log_to_stderr if options.log else None,
        state_path=Path(options.state_path) if options.state_path else None,
        resume=options.resume,
        fingerprint=options.fingerprint,
    )
    result = train_loop(task, loop_cfg)
    result.model.to("cpu")  # checkpoints and segmenters hold CPU weights
    return FitReport(result)


def masked_cross_entropy(logits: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean CE of (B, P, C) logits against (B, P) targets over the valid positions."""
    return F.cross_entropy(logits[valid], target[valid])


def step_encoders_for(data: TrainingData) -> tuple[list[EncoderSpec], Features]:
    """The step encoders PS would read ``data`` with (ps.encoders.choose_encoders via model_config_for;
    the state through its MLP only: these trunks have no periodic embeddings to read it as measured
    values), and the features they read (the action always recorded), as a checkpoint stores them; with
    ``data.encoders_from``, that checkpoint's (`freeze_pretrained_encoders` then loads their weights)."""
    from playseg_core.ps.model import load_model
    from playseg_core.ps.training import model_config_for

    if data.encoders_from:
        model, _ = load_model(data.encoders_from, kinds=("ps", "labeller"))
        model.cfg.check_features(data.features, f"--encoders-from {data.encoders_from}")
        return model.cfg.encoders, model.cfg.features

    config = model_config_for(
        data.features,
        data.domain,
        len(data.instructions),
        read_actions=data.read_actions,
        episodes=data.train,
        overrides=data.encoder_overrides,
        measured_state=False,
    )
    return config.encoders, config.features


def covered_metrics(
    pred_by_episode: Mapping[str, Sequence[Segment]],
    truth_by_episode: Mapping[str, Sequence[Segment]],
    num_steps_by_episode: Mapping[str, int],
) -> dict[str, float | int]:
    """``covered_label_accuracy`` and ``covered_steps`` over episodes (micro-averaged), as
    ps.metrics.evaluate reports the rest."""
    total = LabelCounts(0, 0)
    for episode_id, truth in truth_by_episode.items():
        pred = pred_by_episode.get(episode_id, [])
        total += covered_label_accuracy(pred, truth, num_steps_by_episode[episode_id])
    return {"covered_label_accuracy": total.accuracy, "covered_steps": total.total}


def freeze_pretrained_encoders(encoders: StepEncoders, data: TrainingData) -> None:
    """With ``data.encoders_from``: load that checkpoint's step-encoder weights into ``encoders`` and
    freeze them (built from the same specs by `step_encoders_for`)."""
    if not data.encoders_from:
        return
    from playseg_core.ps.model import load_model

    model, _ = load_model(data.encoders_from, kinds=("ps", "labeller"))
    encoders.load_state_dict(model.encoders.state_dict())
    encoders.requires_grad_(False)
