"""Data-parallel training: N processes, each with its own copy of the model, averaging gradients.

A run is distributed when the environment says so, the way ``torchrun`` sets it up (``WORLD_SIZE`` > 1,
``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR``/``MASTER_PORT``); `launch` sets up the same for N local
processes (`playseg train --nproc N`). `join` then opens the process group: gloo on the CPU, NCCL on
CUDA, where each process takes the card of its local rank.

The loop (loop.py) does the rest: the model's loss runs through torch's DistributedDataParallel, each
process takes its own batches (process r of N trains on batches s+r of each step s, so N processes
see the data of N single-process steps per step and an epoch lasts 1/N of the steps), and process 0
alone evaluates, decides when to stop (broadcast to the others), logs and writes files.
"""

from __future__ import annotations

import gc
import os
import signal
import socket
import sys
import warnings
from collections.abc import Callable
from typing import Any

import torch
import torch.distributed as dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel


def requested_world() -> int:
    """The number of processes the environment asks for (``WORLD_SIZE``; 1 without one)."""
    try:
        return max(1, int(os.environ.get("WORLD_SIZE", "1")))
    except ValueError:
        return 1


def world() -> tuple[int, int]:
    """(number of processes, this one's rank) of the open process group; (1, 0) without one."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size(), dist.get_rank()
    return 1, 0


def is_main() -> bool:
    """True in the process that writes outputs and logs (rank 0, or the only one)."""
    return world()[1] == 0


def join(device: torch.device) -> torch.device:
    """Open the process group the environment asks for (nothing when it asks for one process) and
    return this process's device: on CUDA the card of its local rank."""
    if requested_world() == 1 or (dist.is_available() and dist.is_initialized()):
        return device
    if device.type == "cuda":
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(device)
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo", init_method="env://")
    return device


def leave(wait_for_peers: bool = True) -> None:
    """Close the process group, if one is open; with ``wait_for_peers`` (a run that ended normally in
    every process) once every process has come to close it: a gloo process that tore its group down
    while a peer was still in its last collective was seen to abort ("terminate called without an
    active exception"). A failing process closes it at once (its peers may be in another collective)."""
    if dist.is_available() and dist.is_initialized():
        if wait_for_peers and dist.get_world_size() > 1:
            dist.barrier()
        dist.destroy_process_group()


def agree(flag: bool, device: torch.device) -> bool:
    """Rank 0's ``flag``, in every process (a decision all must take together: stop, out of time)."""
    if world()[0] == 1:
        return flag
    # NCCL moves only CUDA tensors; gloo CPU ones
    value = torch.tensor([1 if flag else 0], dtype=torch.int32, device=device)
    dist.broadcast(value, src=0)
    return bool(value.item())


class _LossOf(nn.Module):
    """A model with its loss as ``forward(batch)``: what DistributedDataParallel wraps, so the gradient
    averaging hooks see the whole loss whatever methods of the model it calls."""

    def __init__(self, model: nn.Module, loss: Callable[[nn.Module, Any], Any]) -> None:
        super().__init__()
        self.model = model
        self._loss = loss

    def forward(self, batch: Any) -> Any:
        return self._loss(self.model, batch)


def data_parallel_loss(model: nn.Module, loss: Callable[[nn.Module, Any], Any]) -> nn.Module:
    """``loss(model, batch)`` as a module whose calls average the gradients over the processes.
    Parameters a batch does not reach (a head some batches skip) are allowed."""
    # A parameter stored in another memory layout (a channels-last kernel) has its gradient copied into
    # the bucket: slower, not wrong; torch warns about it at every backward pass.
    warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
    return DistributedDataParallel(
        _LossOf(model, loss), find_unused_parameters=True, gradient_as_bucket_view=True
    )


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _run_rank(rank: int, nproc: int, port: int, target: Callable[..., int], args: tuple) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        WORLD_SIZE=str(nproc),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        LOCAL_WORLD_SIZE=str(nproc),
    )
    code = target(*args)
    # Data-parallel wrappers sit in reference cycles: freed here, while the group is open, not by the
    # interpreter's teardown, where gloo's threads still holding their work abort the process
    # ("terminate called without an active exception").
    gc.collect()
    leave(wait_for_peers=not code)
    if code:
        raise SystemExit(code)
    # A worker that ended well leaves as multiprocessing's forked workers do, without the teardown.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def launch(nproc: int, target: Callable[..., int], *args: Any) -> int:
    """Run ``target(*args)`` in ``nproc`` local processes set up as ``torchrun`` would (``target`` calls
    `join`); the exit code of the first that failed, else 0. ``target`` must be a module-level function
    (the processes are spawned). Interrupted (Ctrl-C, or SIGTERM turned into KeyboardInterrupt), the
    processes get SIGTERM, so each stops as an interrupted single-process run does (`playseg` turns
    SIGTERM into KeyboardInterrupt; SIGINT may be ignored, as in a shell's background job), and are
    waited for."""
    import logging

    import torch.multiprocessing as mp

    # one process failing (a bad argument fails in all) is reported by its own message, not spawn's
    logging.getLogger("torch.multiprocessing.spawn").setLevel(logging.ERROR)
    # torch's C++ warnings (e.g. that no parameter went unused in a step) go to stderr unfiltered
    os.environ.setdefault("TORCH_CPP_LOG_LEVEL", "ERROR")
    context = mp.spawn(_run_rank, args=(nproc, _free_port(), target, args), nprocs=nproc, join=False)
    try:
        while not context.join():
            pass
    except mp.ProcessExitedException as failed:
        return failed.exit_code if failed.exit_code and failed.exit_code > 0 else 1
    except BaseException:
        _interrupt(context.processes)
        raise
    return 0


def _interrupt(processes: list[Any], grace_s: float = 60.0) -> None:
    """SIGTERM to every live process, then wait for them (SIGKILL after ``grace_s``: one stuck in a
    collective whose peer is gone)."""
    for process in processes:
        if process.is_alive():
            os.kill(process.pid, signal.SIGTERM)
    for process in processes:
        process.join(grace_s)
        if process.is_alive():
            process.kill()
            process.join()
