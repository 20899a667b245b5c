"""Which device a model trains or runs on, and the precision it computes in there.

``auto`` picks CUDA when torch sees one, else the CPU; ``cuda`` and ``cuda:N`` insist on it. On CUDA the
forward passes run under bf16 autocast where the card supports it (no loss scaling needed); on the CPU
everything stays float32, so results there are what they always were.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import Any, TypeVar

import torch

from playseg_core.errors import PlaysegError

DEVICE_CHOICES_HELP = "auto (CUDA when torch sees one, else the CPU), cpu, cuda or cuda:N"


class DeviceError(PlaysegError):
    """A device that cannot be used here (no CUDA, no such card, not a device name)."""


def resolve_device(spec: str | torch.device | None = "auto") -> torch.device:
    """The torch device for ``spec`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``); DeviceError when it is not
    one this machine has."""
    if isinstance(spec, torch.device):
        spec = str(spec)
    text = (spec or "auto").strip().lower()
    if text == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if text == "cpu":
        return torch.device("cpu")
    kind, _, index = text.partition(":")
    if kind != "cuda" or (index and not index.isdigit()):
        raise DeviceError(f"device {spec!r}: expected {DEVICE_CHOICES_HELP}")
    if not torch.cuda.is_available():
        raise DeviceError(f"device {spec!r}: torch sees no CUDA device here (use --device cpu or auto)")
    if index and int(index) >= torch.cuda.device_count():
        raise DeviceError(f"device {spec!r}: torch sees {torch.cuda.device_count()} CUDA device(s)")
    return torch.device(text)


def autocast_dtype(device: torch.device) -> torch.dtype | None:
    """bf16 on a CUDA card that supports it, else None (full precision)."""
    if device.type == "cuda" and torch.cuda.is_bf16_supported():
        return torch.bfloat16
    return None


@contextlib.contextmanager
def mixed_precision(device: torch.device) -> Iterator[None]:
    """Autocast for the forward pass on ``device`` (see `autocast_dtype`); nothing on the CPU."""
    dtype = autocast_dtype(device)
    if dtype is None:
        yield
        return
    with torch.autocast(device_type=device.type, dtype=dtype):
        yield


T = TypeVar("T")


def to_device(value: T, device: torch.device) -> T:
    """``value`` with every tensor inside it (dicts, lists, tuples, dataclasses) moved to ``device``;
    everything else as it is. A no-op on the CPU for CPU tensors."""
    if isinstance(value, torch.Tensor):
        return value.to(device, non_blocking=True)  # type: ignore[return-value]
    if isinstance(value, dict):
        return {key: to_device(item, device) for key, item in value.items()}  # type: ignore[return-value]
    if isinstance(value, list):
        return [to_device(item, device) for item in value]  # type: ignore[return-value]
    if isinstance(value, tuple):
        return (
            type(value)(*(to_device(item, device) for item in value))
            if hasattr(value, "_fields")
            else tuple(to_device(item, device) for item in value)
        )  # type: ignore[return-value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        changes: dict[str, Any] = {
            field.name: to_device(getattr(value, field.name), device)
            for field in dataclasses.fields(value)
            if field.init
        }
        return dataclasses.replace(value, **changes)  # type: ignore[return-value]
    return value
