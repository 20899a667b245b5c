"""Helpers for the node tests: node processes with log files, log polling, a private rclpy context."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from playseg_ros.launch import NODE_KINDS

ROOT = Path(__file__).resolve().parent.parent


def node_env() -> dict[str, str]:
    """The test's environment (private ROS domain) with unbuffered node logs."""
    return dict(os.environ, RCUTILS_LOGGING_BUFFERED_STREAM="0", PYTHONUNBUFFERED="1")


class Processes:
    """Started processes, each logging to its own file; `close()` kills whatever still runs."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: list[subprocess.Popen] = []

    def start(self, args: list[str], log_name: str) -> tuple[subprocess.Popen, Path]:
        log = self.log_dir / f"{log_name}.log"
        with open(log, "ab") as out:
            proc = subprocess.Popen(
                args, cwd=ROOT, env=node_env(), stdout=out, stderr=subprocess.STDOUT, start_new_session=True
            )
        self.procs.append(proc)
        return proc, log

    def node(
        self, kind: str, log_name: str, *ros_args: str, **params: object
    ) -> tuple[subprocess.Popen, Path]:
        """Run the node module of <kind> (launch.NODE_KINDS) with `-p key:=value` for each parameter."""
        args = [sys.executable, "-m", NODE_KINDS[kind], "--ros-args", *ros_args]
        for key, value in params.items():
            args += ["-p", f"{key}:={_param_text(value)}"]
        return self.start(args, log_name)

    def close(self) -> None:
        for proc in self.procs:
            for pid in [*descendants(proc.pid), proc.pid]:
                _kill(pid)
            proc.wait(timeout=10)


def _param_text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(str(v) for v in value) + "]"
    return str(value)


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def descendants(pid: int) -> list[int]:
    """Every live process below `pid` (read from /proc)."""
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        if fields[0] != "Z":
            parents.setdefault(int(fields[1]), []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def wait_for_log(log: Path, pattern: str, timeout: float, proc: subprocess.Popen | None = None) -> re.Match:
    """The first match of `pattern` in the log file; fails with the log's tail on timeout or exit."""
    regex = re.compile(pattern)
    deadline = time.monotonic() + timeout
    while True:
        text = log.read_text(errors="replace") if log.exists() else ""
        match = regex.search(text)
        if match:
            return match
        if proc is not None and proc.poll() is not None:
            raise AssertionError(
                f"{log.name}: exited ({proc.returncode}) before {pattern!r}:\n{text[-3000:]}"
            )
        if time.monotonic() > deadline:
            raise AssertionError(f"{log.name}: no {pattern!r} within {timeout} s:\n{text[-3000:]}")
        time.sleep(0.05)


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 30.0) -> int:
    """Send `sig` and wait for the exit code."""
    proc.send_signal(sig)
    return proc.wait(timeout=timeout)


class RosPeer:
    """An rclpy node of the test process in its own context, spun on demand."""

    def __init__(self, name: str) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.05)
        return True

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
