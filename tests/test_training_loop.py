"""The one training loop (playseg_core/training/loop.py) on a toy regression, and the device helpers."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from playseg_core.training.device import DeviceError, resolve_device, to_device
from playseg_core.training.loop import (
    LoopConfig,
    ResumeError,
    TrainingTask,
    cosine_learning_rate,
    train_loop,
)

torch.set_num_threads(1)


def _toy_task(
    measure_at=None, interrupt_at: int | None = None, seed: int = 0, total: int = 60
) -> TrainingTask:
    """A linear regression whose batch is a function of the step; ``measure_at(step)`` scripts the
    held-out measure (else the real held-out loss); ``interrupt_at``: KeyboardInterrupt at that step."""
    torch.manual_seed(seed)
    model = nn.Sequential(nn.Linear(4, 8), nn.Dropout(0.1), nn.Linear(8, 1))  # dropout: uses torch's RNG
    truth = torch.tensor([[1.0], [-2.0], [0.5], [3.0]])
    steps_seen: list[int] = []

    def batch_at(step: int) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.from_numpy(np.random.default_rng([seed, step]).normal(size=(16, 4))).float()
        return x, x @ truth

    def loss(m: nn.Module, batch: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        steps_seen.append(len(steps_seen))
        if interrupt_at is not None and len(steps_seen) > interrupt_at:
            raise KeyboardInterrupt
        x, y = batch
        value = nn.functional.mse_loss(m(x), y)
        return value, {"loss": float(value.detach())}

    held_x = torch.from_numpy(np.random.default_rng(999).normal(size=(64, 4))).float()

    def evaluate(m: nn.Module) -> dict[str, float]:
        if measure_at is not None:
            return {"val_loss": float(measure_at(len(steps_seen)))}
        return {"val_loss": float(nn.functional.mse_loss(m(held_x), held_x @ truth))}

    return TrainingTask(
        name="toy",
        model=model,
        batch_at=batch_at,
        loss=loss,
        learning_rate=lambda step: cosine_learning_rate(step, 0.05, total),
        optimizer=lambda m: torch.optim.AdamW(m.parameters(), lr=0.05),
        evaluate=evaluate,
    )


def _weights(model: nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


def _same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return len(a) == len(b) and all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_the_learning_rate_warms_up_then_decays_to_zero() -> None:
    rates = [cosine_learning_rate(step, 1.0, 100) for step in range(100)]
    assert rates[0] == pytest.approx(0.2) and rates[4] == pytest.approx(1.0)  # 5 warm-up steps
    assert all(a >= b for a, b in zip(rates[4:], rates[5:], strict=False))
    assert rates[-1] < 0.01 and cosine_learning_rate(100, 1.0, 100) == 0.0


def test_it_learns_and_runs_to_the_cap_without_a_plateau() -> None:
    task = _toy_task()
    result = train_loop(task, LoopConfig(steps=60, eval_every=10, patience=3))
    assert result.steps == 60 and result.stopped == "step cap"
    assert result.history[-1]["val_loss"] < 0.1 * result.history[0]["val_loss"]
    assert [entry["step"] for entry in result.history] == [10, 20, 30, 40, 50, 60]
    assert not result.model.training


def test_early_stopping_stops_on_a_plateau_and_keeps_the_best_weights() -> None:
    # The measure is best after step 20 and worse after: 3 evaluations without improvement stop it.
    result = train_loop(
        _toy_task(measure_at=lambda step: abs(step - 20) + 1), LoopConfig(steps=60, eval_every=5, patience=3)
    )
    assert result.stopped == "plateau" and result.steps == 35
    assert result.best_step == 20 and result.best["val_loss"] == 1.0
    assert "kept step 20" in result.summary() and "stopped by plateau" in result.summary()
    # The weights kept are those of step 20: what a run capped at 20 steps ends with.
    capped = train_loop(
        _toy_task(measure_at=lambda step: 1.0), LoopConfig(steps=60, eval_every=20, patience=1)
    )
    assert capped.best_step == 20
    assert _same(_weights(result.model), _weights(capped.model))


def test_patience_also_waits_a_number_of_steps_since_the_best() -> None:
    # A measure that dips for a few evaluations and then improves again (a small val split's noise):
    # best at 20, worse at 25-40, better at 45. Three evaluations alone stop it at 35; patience_steps 25
    # keeps it going past the dip to the better weights of step 45.
    def measure_at(step: int) -> float:
        return 10.0 - step / 5 if step <= 20 else (9.0 if step < 45 else 1.0)

    impatient = train_loop(_toy_task(measure_at=measure_at), LoopConfig(steps=60, eval_every=5, patience=3))
    assert impatient.stopped == "plateau" and impatient.steps == 35 and impatient.best_step == 20
    waiting = LoopConfig(steps=80, eval_every=5, patience=3, patience_steps=25)
    result = train_loop(_toy_task(measure_at=measure_at), waiting)
    assert result.best_step == 45 and result.best["val_loss"] == 1.0
    # from step 45 on nothing improves: 3 evaluations would be 60, 25 steps make it 70
    assert result.stopped == "plateau" and result.steps == 70


def test_a_plateau_reached_at_the_cap_is_reported_as_the_cap() -> None:
    # Best at 20, patience 3 evaluations of 5: the plateau holds at 35, the cap's step.
    result = train_loop(
        _toy_task(measure_at=lambda step: abs(step - 20) + 1), LoopConfig(steps=35, eval_every=5, patience=3)
    )
    assert result.steps == 35 and result.stopped == "step cap" and result.best_step == 20
    assert "stopped by step cap" in result.summary()


def test_max_steps_and_max_minutes_bound_the_run() -> None:
    assert train_loop(_toy_task(), LoopConfig(steps=7)).steps == 7
    result = train_loop(_toy_task(), LoopConfig(steps=1000, eval_every=500, max_minutes=1e-9))
    assert result.steps == 1 and result.stopped == "max minutes"
    assert len(result.history) == 1  # evaluated once before stopping: the weights kept are measured


def test_an_interrupted_run_resumes_to_what_the_uninterrupted_run_gives(tmp_path: Path) -> None:
    state = tmp_path / "run.train-state"
    whole = train_loop(_toy_task(), LoopConfig(steps=50, eval_every=10, patience=5, fingerprint="a"))
    with pytest.raises(KeyboardInterrupt):
        train_loop(
            _toy_task(interrupt_at=33), LoopConfig(steps=50, eval_every=10, state_path=state, fingerprint="a")
        )
    assert state.is_file()  # written at step 30
    resumed = train_loop(
        _toy_task(),
        LoopConfig(steps=50, eval_every=10, patience=5, state_path=state, resume=True, fingerprint="a"),
    )
    assert resumed.steps == 50 and not state.exists()  # removed once the run is done
    assert _same(_weights(whole.model), _weights(resumed.model))
    assert [h["val_loss"] for h in resumed.history] == [h["val_loss"] for h in whole.history]


def test_a_resume_file_of_another_run_or_none_is_one_clear_error(tmp_path: Path) -> None:
    state = tmp_path / "run.train-state"
    with pytest.raises(ResumeError, match="no training state"):
        train_loop(_toy_task(), LoopConfig(steps=5, state_path=state, resume=True))
    with pytest.raises(KeyboardInterrupt):
        train_loop(
            _toy_task(interrupt_at=3), LoopConfig(steps=9, eval_every=2, state_path=state, fingerprint="a")
        )
    with pytest.raises(ResumeError, match="other settings or data"):
        train_loop(_toy_task(), LoopConfig(steps=9, state_path=state, resume=True, fingerprint="b"))
    state.write_bytes(b"not a torch file")
    with pytest.raises(ResumeError, match="not a readable training state"):
        train_loop(_toy_task(), LoopConfig(steps=9, state_path=state, resume=True, fingerprint="a"))


def test_batches_prepared_on_a_thread_give_the_same_run() -> None:
    plain = train_loop(_toy_task(), LoopConfig(steps=30, eval_every=10, prefetch=False))
    ahead = train_loop(_toy_task(), LoopConfig(steps=30, eval_every=10, prefetch=True))
    assert _same(_weights(plain.model), _weights(ahead.model))


def test_devices_are_resolved_or_refused_in_one_line() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(DeviceError, match="expected auto"):
        resolve_device("gpu")
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="no CUDA device"):
            resolve_device("cuda:0")


@dataclass
class _Pair:
    a: torch.Tensor
    b: dict[str, torch.Tensor]
    name: str


def test_to_device_moves_every_tensor_inside_a_batch() -> None:
    pair = _Pair(torch.zeros(2), {"x": torch.ones(1)}, "kept")
    moved = to_device([pair, (torch.zeros(1), 3)], torch.device("meta"))
    assert moved[0].a.device.type == "meta" and moved[0].b["x"].device.type == "meta"
    assert moved[0].name == "kept" and moved[1][1] == 3 and moved[1][0].device.type == "meta"


def test_a_cap_below_one_step_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one step"):
        train_loop(_toy_task(), LoopConfig(steps=0))
    assert math.isfinite(cosine_learning_rate(0, 1.0, 1))


def _train_toy_in_group(out: str) -> int:
    """One process of a data-parallel toy run (distributed.launch): joins the gloo group, trains, and
    process 0 writes its result."""
    from playseg_core.training import distributed

    torch.set_num_threads(1)
    distributed.join(torch.device("cpu"))
    result = train_loop(_toy_task(total=400), LoopConfig(steps=400, eval_every=50))
    processes, rank = distributed.world()
    if rank == 0:
        torch.save(
            {
                "processes": processes,
                "history": result.history,
                "summary": result.summary(),
                "best": result.best,
            },
            out,
        )
    return 0


@pytest.mark.slow
def test_two_gloo_processes_train_to_the_quality_of_one(tmp_path: Path) -> None:
    from playseg_core.training import distributed

    one = train_loop(_toy_task(total=400), LoopConfig(steps=400, eval_every=50))
    out = tmp_path / "two.pt"
    assert distributed.launch(2, _train_toy_in_group, str(out)) == 0
    two = torch.load(out, weights_only=True)
    assert two["processes"] == 2 and "(2 processes)" in two["summary"]
    # the same batches seen in half the optimizer steps (each step averages two processes' gradients):
    # evaluations at the same points of the data, the held-out loss as low as one process gets it
    assert [entry["step"] for entry in two["history"]] == [50.0 * n for n in range(1, 9)]
    assert two["best"]["val_loss"] < 0.1 * two["history"][0]["val_loss"]
    assert two["best"]["val_loss"] <= 2 * one.best["val_loss"] + 1e-3
