"""A robot bag read and converted by a child Python whose imports a finder blocks: the shared body of the
tests that the I/O part runs without ROS 2 (tests/test_architecture.py, tests/test_io_install.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

WATCHED = ("rclpy", "playseg_msgs", "torch", "ray")


def run_blocked(
    blocker: str, bag: Path, mapping: Path, out: Path, extra: str = ""
) -> subprocess.CompletedProcess[str]:
    """Run ``blocker`` (source that installs an import finder), then ``extra``, then `playseg convert` of
    ``bag`` into ``out/data`` and ``out/lerobot``; the child's last line lists the WATCHED packages it
    imported. Asserts that it succeeded and wrote both datasets."""
    code = (
        blocker
        + extra
        + (
            "from playseg_ros.cli import main\n"
            f"common = [{str(bag)!r}, '--mapping', {str(mapping)!r}, '--quiet']\n"
            f"assert main(['convert', *common, '--out', {str(out / 'data')!r}]) == 0\n"
            f"assert main(['convert', *common, '--out', {str(out / 'lerobot')!r}, '--format', 'lerobot']) == 0\n"
            f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({WATCHED!r})))\n"
        )
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=out)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (out / "data" / "meta" / "info.json").is_file()
    assert (out / "lerobot" / "meta" / "info.json").is_file()
    return done
