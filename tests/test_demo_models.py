"""The demo's tabletop sample model as `make models` trains it (`playseg train`'s defaults on generated
play, at a tiny budget here): the checkpoint names its recipe, which the demo checks before using it, and
keeps its figures on the held-out test split, which the demo prints next to the live ones."""

from __future__ import annotations

from pathlib import Path

import pytest

from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.model import load_model
from playseg_ros.demo import _recipe_text, shipped_model, train_tabletop_model


@pytest.mark.slow
def test_the_tabletop_model_keeps_its_recipe_and_test_figures(tmp_path: Path) -> None:
    recipe = {"preset": "tiny", "seed": 3, "max_steps": 10}
    model = train_tabletop_model(recipe, tmp_path, tmp_path / "tabletop-ps.pt")
    _, meta = load_model(model, ("ps",))
    data = PlayDataset.open(tmp_path / "tabletop-tiny-3")
    test = list(data.episodes("test", truth=True))
    figures = meta["test"]
    assert figures["episodes"] == len(test) > 0
    assert figures["true_segments"] == sum(len(episode.segments) for episode in test) > 0
    for key in ("f1_exact", "f1_tol2", "label_accuracy"):
        assert 0.0 <= figures[key] <= 1.0, (key, figures)
    assert figures["f1_exact"] <= figures["f1_tol2"]
    assert meta["trained_on"] == _recipe_text(recipe) and "--max-steps 10" in meta["trained_on"]
    assert shipped_model(model, _recipe_text(recipe)) == model
    assert shipped_model(model, _recipe_text({**recipe, "seed": 4})) is None  # another recipe: retrain
