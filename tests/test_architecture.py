"""The shape of the code: generic machinery never depends on a domain; one checkpoint format for all models."""

from __future__ import annotations

import ast
import importlib
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from ros_free_run import run_blocked

from playseg_core.checkpoint import CheckpointError, read_checkpoint
from playseg_core.data.features import ACTION, STATE, Feature, FeatureError, Features
from playseg_core.domains import Domain, load_domain, register_domain
from playseg_core.domains.babyai.play import PlayConfig
from playseg_core.domains.babyai.policy import PolicyConfig, PolicyNet, load_policy, save_policy
from playseg_core.domains.babyai.spec import CAMERA, INSTRUCTIONS
from playseg_core.errors import PlaysegError
from playseg_core.ps.model import LabelModel, PSModel, load_model, save_model
from playseg_core.ps.training import model_config_for

ROOT = Path(__file__).resolve().parent.parent
DOMAIN_DIRS = (
    ROOT / "playseg_core" / "domains",
    ROOT / "playseg_ros" / "babyai",
    ROOT / "playseg_ros" / "tabletop",  # the tabletop domain's ROS side: its robot bags
)


def _python_files() -> list[Path]:
    return sorted(p for package in ("playseg_core", "playseg_ros") for p in (ROOT / package).rglob("*.py"))


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def _in_a_domain(path: Path) -> bool:
    return (
        any(path.is_relative_to(d) for d in DOMAIN_DIRS) and path != ROOT / "playseg_core/domains/__init__.py"
    )


def test_no_module_outside_a_domain_imports_minigrid_or_a_domain_package() -> None:
    offenders = []
    for path in _python_files():
        if _in_a_domain(path):
            continue
        for name in _imports(path):
            if name.split(".")[0] == "minigrid" or name.startswith("playseg_core.domains."):
                offenders.append(f"{path.relative_to(ROOT)} imports {name}")
    assert offenders == []


def test_playseg_core_never_imports_ros() -> None:
    for path in (ROOT / "playseg_core").rglob("*.py"):
        roots = {name.split(".")[0] for name in _imports(path)}
        assert not roots & {"rclpy", "playseg_ros"}, path


def test_generic_code_names_no_babyai_facts() -> None:
    """Grid tiles, the 36 instructions, the 7 actions, 64x64 frames live in the BabyAI package only
    (only a default names the domain: the trainer's policy, `playseg generate`'s domain, the node table)."""
    facts = re.compile(r"\b(babyai|BabyAI|minigrid|tile|36|7 actions|64x64|64, 64)\b")
    allowed = {  # what names a domain without depending on it: the default policy, the node registry
        "playseg_ros/nodes/trainer.py": {"babyai"},
        "playseg_ros/launch.py": {"babyai"},
        "playseg_ros/cli.py": {"babyai"},
    }
    offenders = []
    for path in _python_files():
        relative = str(path.relative_to(ROOT))
        if _in_a_domain(path) or relative == "playseg_ros/demo.py":  # the demo runs the BabyAI sample bags
            continue
        found = set(facts.findall(path.read_text())) - allowed.get(relative, set())
        if found:
            offenders.append(f"{relative}: {sorted(found)}")
    assert offenders == []


def _other_features(features: Features) -> Features:
    return features.with_camera(Feature(CAMERA, "image", "uint8", (96, 96, 3)))


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ps", "labeller"])
def test_segmentation_checkpoints_round_trip_and_refuse_other_features(tmp_path: Path, kind: str) -> None:
    features = PlayConfig().features
    torch.manual_seed(0)
    cfg = model_config_for(features, "babyai", len(INSTRUCTIONS))
    model = (PSModel if kind == "ps" else LabelModel)(cfg, list(INSTRUCTIONS)).eval()
    save_model(tmp_path / "m.pt", model, {"note": kind})
    loaded, meta = load_model(tmp_path / "m.pt")
    assert type(loaded) is type(model) and meta == {"note": kind}
    for name, tensor in model.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[name], tensor)
    checkpoint = read_checkpoint(tmp_path / "m.pt")
    assert checkpoint.kind == kind and checkpoint.features.cameras == [CAMERA]
    checkpoint.check_features(features)
    with pytest.raises(FeatureError, match=f"m.pt reads {CAMERA}: image \\[64, 64, 3\\].*\\[96, 96, 3\\]"):
        checkpoint.check_features(_other_features(features))


def test_policy_checkpoint_round_trips_and_refuses_other_features(tmp_path: Path) -> None:
    torch.manual_seed(0)
    policy = PolicyNet(PolicyConfig(channels=8)).eval()
    save_policy(tmp_path / "p.pt", policy, {"version": 3})
    loaded, meta = load_policy(tmp_path / "p.pt")
    assert meta == {"version": 3} and loaded.config == policy.config
    states = np.random.default_rng(0).integers(0, 6, size=(4, 8, 8, 3)).astype(np.uint8)
    instructions = list(INSTRUCTIONS[:4])
    np.testing.assert_array_equal(
        loaded.act({STATE: states}, instructions), policy.act({STATE: states}, instructions)
    )
    checkpoint = read_checkpoint(tmp_path / "p.pt", kinds=("policy",))
    checkpoint.check_features(PlayConfig().features)  # BabyAI data has the grid state and the 7 actions
    continuous = PlayConfig().features.with_action(Feature(ACTION, "action", "float32", (2,)))
    with pytest.raises(FeatureError, match="p.pt reads action: action \\(discrete, 7 values\\)"):
        checkpoint.check_features(continuous)
    with pytest.raises(CheckpointError, match="p.pt: a 'policy' checkpoint, expected ps or labeller"):
        load_model(tmp_path / "p.pt")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the playseg modules it imports when it runs (at the top or inside a function; not under
    ``if TYPE_CHECKING:``, which never runs): ``from package import module`` counts as the module."""
    modules = {_module_name(path): path for path in _python_files()}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        typing_only = {
            id(inner)
            for node in ast.walk(tree)
            if isinstance(node, ast.If)
            and isinstance(node.test, ast.Name)
            and node.test.id == "TYPE_CHECKING"
            for statement in node.body
            for inner in ast.walk(statement)
        }
        imported = set()
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.Import):
                imported.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    imported.add(full if full in modules else node.module)
        graph[name] = {other for other in imported if other in modules and other != name}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected groups of more than one module (Tarjan's algorithm, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                group = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    group.append(member)
                    if member == node:
                        break
                if len(group) > 1:
                    found.append(sorted(group))
    return found


def test_the_circle_finder_finds_a_circle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _circles(graph) == [["a", "b", "c"]]


@pytest.mark.slow
def test_no_import_circles_among_playseg_modules() -> None:
    """Modules form layers: no module reaches itself through imports, not even through one made inside a
    function (a circle hidden that way still ties the two modules together)."""
    assert _circles(_import_graph()) == []


@pytest.mark.slow
def test_product_code_raises_playseg_errors_not_bare_value_errors() -> None:
    """A check of playseg's raises PlaysegError (or its module's subclass), so the command line shows a
    bug's ValueError with its traceback instead of passing it off as bad input."""
    offenders = []
    for path in _python_files():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call):
                function = node.exc.func
                if isinstance(function, ast.Name) and function.id == "ValueError":
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


@pytest.mark.slow
def test_every_error_class_descends_from_playseg_error() -> None:
    offenders = []
    for path in _python_files():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and node.name.endswith(("Error", "NotRecorded")):
                module = importlib.import_module(_module_name(path))
                if not issubclass(getattr(module, node.name), PlaysegError):
                    offenders.append(f"{path.relative_to(ROOT)}: {node.name}")
    assert offenders == []


@pytest.mark.slow
def test_loading_a_domain_imports_no_experiment_code() -> None:
    """A node loading a checkpoint reaches the data's domain; that must not pull in the experiment runner."""
    code = (
        "import sys\n"
        "from playseg_core.domains import load_domain\n"
        "for name in ('babyai', 'tabletop'):\n"
        "    assert load_domain(name).name == name\n"
        "print(sorted(m for m in sys.modules if m.startswith('playseg_core.experiment')))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]", done.stdout + done.stderr


def test_every_domain_registers_one_typed_domain() -> None:
    for name in ("babyai", "tabletop"):
        domain = load_domain(name)
        assert isinstance(domain, Domain) and load_domain(name) is domain and domain.policies
    with pytest.raises(PlaysegError, match="unknown domain 'atlantis'"):
        load_domain("atlantis")
    with pytest.raises(PlaysegError, match="registered twice"):
        register_domain(Domain(name="babyai"))


BLOCK_ROS = """
import importlib.abc, sys

class BlockRos(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("rclpy", "playseg_msgs"):
            raise ImportError(f"{name} is blocked")
        return None

sys.meta_path.insert(0, BlockRos())
"""


@pytest.mark.slow
def test_bag_io_convert_and_the_lerobot_export_run_without_rclpy_or_playseg_msgs(tmp_path: Path) -> None:
    """The I/O half of playseg_ros needs no ROS: with rclpy and playseg_msgs unimportable, a robot bag is
    read and converted into a dataset and into LeRobot v3 (bag recovery imports as well)."""
    bag = tmp_path / "tabletop-0"
    shutil.copytree(ROOT / "bags" / "tabletop" / "tabletop-0", bag)
    mapping = ROOT / "bags" / "tabletop" / "mapping_truth.yaml"
    reading = (
        "from playseg_ros.bag import BagReader, recover_bag\n"
        "from playseg_ros.convert.lerobot import export_lerobot\n"
        f"with BagReader({str(bag)!r}) as reader:\n"
        "    assert sum(1 for _ in reader.messages()) > 0\n"
    )
    done = run_blocked(BLOCK_ROS, bag, mapping, tmp_path, extra=reading)
    assert done.stdout.strip().splitlines()[-1] == "[]"
