"""The one training loop: PS, the labelling model, the window baselines and the policies all train here.

nanoGPT-style: each method supplies a `TrainingTask` (its model, its batch for a step, its loss, and
optionally a held-out evaluation) and the loop does the rest, the same way for every method:

- the learning rate of each step comes from a function of the step (`cosine_learning_rate` by default);
- every ``eval_every`` steps the held-out measure is computed; the best weights are kept, and the run
  stops when the measure has not improved for ``patience`` evaluations (early stopping), at the step
  cap or after ``max_minutes`` (an interrupt propagates: the caller reports it, the resume file stays);
- the state (model, optimiser, step, RNG, best weights) is written every evaluation to a resume file, so
  a killed run continues where it was (`LoopConfig.resume`), giving what the uninterrupted run gives;
- batches are moved to the device, the forward pass runs in its mixed precision (device.py), and on a
  GPU the next batch is prepared on a second thread while the current one trains;
- in a process group (distributed.py) the loss runs through DistributedDataParallel and each process
  takes its own batches; steps then count batches, so the cap, the evaluations and the learning rate
  follow the data seen whatever the number of processes.

A step's batch must be a function of the step number alone (`TrainingTask.batch_at`): that is what makes
resuming exact and preparing batches ahead safe.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn
from tqdm import tqdm

from playseg_core.errors import PlaysegError
from playseg_core.training import distributed
from playseg_core.training.device import mixed_precision, to_device

RESUME_FORMAT = "playseg-training-state"

LossResult = tuple[torch.Tensor, dict[str, float]]
"""A batch's loss (what is minimised) and the figures to log for it (at least ``loss``)."""


def cosine_learning_rate(step: int, peak: float, total: int, warmup_share: float = 0.05) -> float:
    """Learning rate of optimizer step ``step`` (0-based) of ``total``: a linear warm-up to ``peak`` over
    the first ``warmup_share`` of the steps, then a cosine down to zero at ``total``."""
    warmup = max(1, int(total * warmup_share))
    if step < warmup:
        return peak * (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return peak * 0.5 * (1.0 + math.cos(math.pi * progress))


@dataclass
class TrainingTask:
    """What a method gives the loop.

    ``batch_at(step)``: the batch of optimizer step ``step`` (0-based), a function of the step alone;
    ``loss(model, batch)``: its loss and figures; ``evaluate(model)``: held-out figures, the one under
    ``measure`` (lower is better) decides the best weights and early stopping; ``learning_rate(step)``;
    ``optimizer(model)``: a fresh optimiser (AdamW by default, built by the method).
    """

    name: str
    model: nn.Module
    batch_at: Callable[[int], Any]
    loss: Callable[[nn.Module, Any], LossResult]
    learning_rate: Callable[[int], float]
    optimizer: Callable[[nn.Module], torch.optim.Optimizer]
    evaluate: Callable[[nn.Module], dict[str, float]] | None = None
    measure: str = "val_loss"


@dataclass
class LoopConfig:
    steps: int  # the step cap
    eval_every: int = 0  # evaluate every so many steps (0: only after the last)
    patience: int = 0  # evaluations without improvement that end the run (0: never early)
    patience_steps: int = 0  # ... and at least this many steps since the best (a noisy measure's dips)
    min_improvement: float = 1e-3  # relative: a measure must beat the best by this share to count
    max_minutes: float | None = None
    grad_clip: float | None = 5.0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    prefetch: bool | None = None  # prepare the next batch on a thread (None: on CUDA only)
    progress: bool = False  # a progress bar: step / cap, loss, the measure, ETA
    log: Callable[[str], None] | None = None  # one line per evaluation
    state_path: Path | None = None  # the resume file, written every evaluation, removed at the end
    resume: bool = False  # continue from ``state_path``
    fingerprint: str = ""  # what the run is (settings, data): a resume file of another run is refused


@dataclass
class LoopResult:
    model: nn.Module
    steps: int  # batches trained on per process group: optimizer steps x processes
    cap: int  # the step cap
    stopped: str  # why it stopped: "plateau", "step cap", "max minutes"
    best_step: int | None  # the step whose weights were kept (None: no evaluation, the last)
    best: dict[str, float]  # that evaluation's figures
    history: list[dict[str, float]]  # one entry per evaluation: step, lr, train loss, held-out figures
    seconds: float
    measure: str
    processes: int = 1

    def summary(self) -> str:
        """One line: steps against the cap, why it stopped, and which weights were kept."""
        kept = (
            f"; kept step {self.best_step} ({self.measure} {self.best[self.measure]:.4f})"
            if self.best_step is not None and self.measure in self.best
            else ""
        )
        parallel = f" ({self.processes} processes)" if self.processes > 1 else ""
        return (
            f"{self.steps} of at most {self.cap} steps{parallel}, stopped by {self.stopped}{kept}, "
            f"{self.seconds:.0f} s"
        )


class ResumeError(PlaysegError):
    """A resume file that is missing, unreadable or of another run; the message names it."""


@dataclass
class _Progress:
    """What the loop carries from step to step, and what a resume file holds."""

    step: int = 0
    best_measure: float = math.inf
    best_step: int | None = None
    best: dict[str, float] = field(default_factory=dict)
    best_state: dict[str, torch.Tensor] | None = None
    since_best: int = 0
    history: list[dict[str, float]] = field(default_factory=list)
    seconds: float = 0.0
    losses: list[float] = field(default_factory=list)  # train losses since the last evaluation
    shown: str = ""  # the last evaluation, as the progress bar shows it


def log_to_stderr(line: str) -> None:
    """A `LoopConfig.log`: each line on stderr, flushed (it interleaves with a progress bar)."""
    print(line, file=sys.stderr, flush=True)


def _cpu_state(model: nn.Module) -> dict[str, torch.Tensor]:
    return {key: value.detach().to("cpu", copy=True) for key, value in model.state_dict().items()}


def _partial(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def _save_state(
    path: Path, cfg: LoopConfig, progress: _Progress, model: nn.Module, optimizer: torch.optim.Optimizer
) -> None:
    state = {
        "format": RESUME_FORMAT,
        "fingerprint": cfg.fingerprint,
        "step": progress.step,
        "best_measure": progress.best_measure,
        "best_step": -1 if progress.best_step is None else progress.best_step,
        "best": progress.best,
        "best_state": progress.best_state or {},
        "since_best": progress.since_best,
        "history": progress.history,
        "seconds": progress.seconds,
        "model": _cpu_state(model),
        "optimizer": optimizer.state_dict(),
        "torch_rng": torch.get_rng_state(),
        "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }
    partial = _partial(path)
    torch.save(state, partial)
    os.replace(partial, path)


def _load_state(path: Path, cfg: LoopConfig, model: nn.Module, optimizer: torch.optim.Optimizer) -> _Progress:
    if not path.is_file():
        raise ResumeError(f"--resume: no training state {path} (nothing to resume; train without --resume)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - any unreadable file is the same user error
        raise ResumeError(
            f"--resume: {path} is not a readable training state ({type(error).__name__})"
        ) from None
    if not isinstance(state, dict) or state.get("format") != RESUME_FORMAT:
        raise ResumeError(f"--resume: {path} is not a playseg training state")
    if state.get("fingerprint") != cfg.fingerprint:
        raise ResumeError(
            f"--resume: {path} was written by a run with other settings or data; remove it to start afresh"
        )
    try:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
    except (KeyError, RuntimeError, ValueError) as error:
        raise ResumeError(f"--resume: {path} does not fit this model ({type(error).__name__})") from None
    torch.set_rng_state(state["torch_rng"])
    if state["cuda_rng"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda_rng"])
    best_step = int(state["best_step"])
    return _Progress(
        step=int(state["step"]),
        best_measure=float(state["best_measure"]),
        best_step=None if best_step < 0 else best_step,
        best=dict(state["best"]),
        best_state=dict(state["best_state"]) or None,
        since_best=int(state["since_best"]),
        history=list(state["history"]),
        seconds=float(state["seconds"]),
    )


@contextmanager
def _batches(task: TrainingTask, cfg: LoopConfig, first: int, stride: int) -> Iterator[Callable[[int], Any]]:
    """``get(step)`` -> the step's batch on the device; with prefetching, the next one (step+stride) is
    being made meanwhile."""
    prefetch = cfg.device.type == "cuda" if cfg.prefetch is None else cfg.prefetch
    if not prefetch:
        yield lambda step: to_device(task.batch_at(step), cfg.device)
        return
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{task.name}-batches")
    pending: dict[int, Future] = {first: pool.submit(task.batch_at, first)}

    def get(step: int) -> Any:
        future = pending.pop(step, None) or pool.submit(task.batch_at, step)
        batch = future.result()
        pending.clear()
        pending[step + stride] = pool.submit(task.batch_at, step + stride)
        return to_device(batch, cfg.device)

    try:
        yield get
    finally:
        for future in pending.values():
            future.cancel()
        pool.shutdown(wait=True)


def _evaluate(task: TrainingTask, model: nn.Module, cfg: LoopConfig) -> dict[str, float]:
    if task.evaluate is None:
        return {}
    model.eval()
    with torch.no_grad(), mixed_precision(cfg.device):
        figures = task.evaluate(model)
    model.train()
    return figures


def train_loop(task: TrainingTask, cfg: LoopConfig) -> LoopResult:
    """Train ``task.model`` for at most ``cfg.steps`` steps (see the module's docstring); the returned
    model holds the best evaluated weights (the last ones without an evaluation), in eval mode. In a
    process group, process 0's model is the one to keep."""
    if cfg.steps < 1:
        raise PlaysegError(f"{task.name}: a run needs at least one step, got a cap of {cfg.steps}")
    processes, rank = distributed.world()
    main = rank == 0
    model = task.model.to(cfg.device)
    optimizer = task.optimizer(model)
    progress = _Progress()
    if cfg.resume and cfg.state_path is not None:
        progress = _load_state(cfg.state_path, cfg, model, optimizer)
        if main:  # always said: a resumed run must not pass for a fresh one
            (cfg.log or log_to_stderr)(f"[{task.name}] resumed at step {progress.step} from {cfg.state_path}")
    loss_of = (
        distributed.data_parallel_loss(model, task.loss)
        if processes > 1
        else (lambda batch: task.loss(model, batch))
    )
    stopped = "step cap"
    began = time.perf_counter() - progress.seconds
    bar = tqdm(
        total=cfg.steps, initial=progress.step, desc=task.name, file=sys.stderr,
        disable=not (cfg.progress and main), leave=False, unit="step", dynamic_ncols=True,
    )  # fmt: skip
    model.train()
    with _batches(task, cfg, progress.step + rank, processes) as batch_of:
        while progress.step < cfg.steps:
            step = progress.step
            for group in optimizer.param_groups:
                group["lr"] = task.learning_rate(step)
            batch = batch_of(step + rank)
            with mixed_precision(cfg.device):
                loss, figures = loss_of(batch)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip is not None:
                nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            progress.step = step + processes
            progress.losses.append(float(figures.get("loss", float(loss.detach()))))
            bar.update(processes)
            bar.set_postfix_str(f"loss {progress.losses[-1]:.4f}{progress.shown}", refresh=False)
            last = progress.step >= cfg.steps
            out_of_time = cfg.max_minutes is not None and time.perf_counter() - began >= 60 * cfg.max_minutes
            if cfg.max_minutes is not None:
                out_of_time = distributed.agree(out_of_time, cfg.device)  # the clocks differ
            due = bool(cfg.eval_every) and progress.step // cfg.eval_every > step // cfg.eval_every
            if due or last or out_of_time:
                progress.seconds = time.perf_counter() - began
                plateau = _record_evaluation(task, model, cfg, progress, bar) if main else False
                # At the cap the cap stopped it, whatever the plateau says (every process agrees on `last`).
                if not last and distributed.agree(plateau, cfg.device):
                    stopped = "plateau"
                    break
                if cfg.state_path is not None and not last and main:
                    _save_state(cfg.state_path, cfg, progress, model, optimizer)
            if out_of_time:
                stopped = "max minutes"
                break
    bar.close()
    if progress.best_state is not None:
        model.load_state_dict(progress.best_state)
    model.eval()
    if cfg.state_path is not None and main:
        cfg.state_path.unlink(missing_ok=True)
        _partial(cfg.state_path).unlink(missing_ok=True)  # one a kill cut short
    return LoopResult(
        model=model,
        steps=progress.step,
        cap=cfg.steps,
        stopped=stopped,
        best_step=progress.best_step,
        best=progress.best,
        history=progress.history,
        seconds=time.perf_counter() - began,
        measure=task.measure,
        processes=processes,
    )


def _record_evaluation(
    task: TrainingTask, model: nn.Module, cfg: LoopConfig, progress: _Progress, bar: tqdm
) -> bool:
    """Evaluate, keep the weights if they are the best so far, log; True when patience has run out."""
    figures = _evaluate(task, model, cfg)
    entry = {
        "step": float(progress.step),
        "lr": float(task.learning_rate(progress.step - 1)),
        "train_loss": float(sum(progress.losses) / max(1, len(progress.losses))),
        **{key: float(value) for key, value in figures.items()},
    }
    progress.losses.clear()
    progress.history.append(entry)
    measure = figures.get(task.measure)
    if measure is not None and math.isfinite(measure):
        if progress.best_step is None or measure < progress.best_measure - cfg.min_improvement * abs(
            progress.best_measure
        ):
            progress.best_measure, progress.best_step, progress.best = measure, progress.step, dict(entry)
            progress.best_state = _cpu_state(model)
            progress.since_best = 0
        else:
            progress.since_best += 1
        progress.shown = f", {task.measure} {measure:.4f} (best {progress.best_measure:.4f})"
    if cfg.log:
        shown = " ".join(f"{key} {value:.4f}" for key, value in entry.items() if key not in ("step", "lr"))
        cfg.log(f"[{task.name}] step {progress.step}/{cfg.steps} lr {entry['lr']:.2e} {shown}")
    if not cfg.patience or progress.since_best < cfg.patience:
        return False
    return progress.best_step is None or progress.step - progress.best_step >= cfg.patience_steps
