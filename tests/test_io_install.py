"""The ROS-free I/O part installs alone (requirements-io.txt, the `io` extra; docs/setup.md): its pins are
requirements.txt's, and `playseg bag` and `playseg convert` run with every other installed distribution
unimportable. `make io-check` does the same in a real clean environment."""

from __future__ import annotations

import importlib.metadata as metadata
import re
from pathlib import Path

from ros_free_run import run_blocked

ROOT = Path(__file__).resolve().parent.parent


def _pins(name: str) -> dict[str, str]:
    lines = (line.split("#")[0].strip() for line in (ROOT / name).read_text().splitlines())
    return {_normal(pin.split("==")[0]): pin.split("==")[1] for pin in lines if pin}


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _closure(roots: list[str]) -> set[str]:
    """The distributions that pip installs for ``roots`` (their requirements without extras, here)."""
    seen: set[str] = set()
    stack = list(roots)
    while stack:
        name = _normal(stack.pop())
        if name in seen:
            continue
        try:
            requires = metadata.distribution(name).requires or []
        except metadata.PackageNotFoundError:
            continue  # a platform-only requirement (colorama on Windows)
        seen.add(name)
        stack += [re.split(r"[ ;<>=!~\[(]", r, maxsplit=1)[0] for r in requires if "extra ==" not in r]
    return seen


def test_the_io_pins_are_requirements_txt_pins_without_ros_or_torch() -> None:
    io, full = _pins("requirements-io.txt"), _pins("requirements.txt")
    assert io and all(full.get(name) == version for name, version in io.items()), (io, full)
    assert not [name for name in io if name.startswith("ros-") or name in ("torch", "catkin-pkg")]


BLOCK_OTHERS = """
import importlib.abc, sys

ALLOWED = {allowed!r}
OWNERS = {owners!r}

class BlockOthers(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        owners = OWNERS.get(name.split(".")[0])
        if owners and not owners & ALLOWED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (not in requirements-io.txt)", name=name)
        return None

sys.meta_path.insert(0, BlockOthers())
"""


def test_bag_and_convert_need_only_the_io_pins(tmp_path: Path) -> None:
    allowed = _closure(list(_pins("requirements-io.txt"))) | {"playseg-ros"}
    owners = {
        module: {_normal(name) for name in names}
        for module, names in metadata.packages_distributions().items()
        if module not in ("playseg_core", "playseg_ros")
    }
    assert (
        "torch" in owners and "rclpy" in owners
    )  # the full install is here: the block below means something
    bag = ROOT / "bags" / "tabletop" / "tabletop-0"
    mapping = ROOT / "bags" / "tabletop" / "mapping.yaml"
    more = (
        "from playseg_ros.cli import main\n"
        f"assert main(['bag', 'info', {str(bag)!r}]) == 0\n"
        f"assert main(['convert', {str(bag)!r}, '--out', 'seg', '--mapping', {str(mapping)!r}, '--segment', 'm.pt']) == 1\n"
    )
    done = run_blocked(
        BLOCK_OTHERS.format(allowed=allowed, owners=owners), bag, mapping, tmp_path, extra=more
    )
    assert done.stdout.strip().splitlines()[-1] == "[]"
    assert "needs " in done.stderr and "Traceback" not in done.stderr, done.stderr
