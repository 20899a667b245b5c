"""The shape of the code: generic machinery never depends on a domain; one checkpoint format for all models."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from playseg_core.checkpoint import CheckpointError, read_checkpoint
from playseg_core.data.features import ACTION, STATE, Feature, FeatureError, Features
from playseg_core.domains.babyai.play import PlayConfig
from playseg_core.domains.babyai.policy import PolicyConfig, PolicyNet, load_policy, save_policy
from playseg_core.domains.babyai.spec import CAMERA, INSTRUCTIONS
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
