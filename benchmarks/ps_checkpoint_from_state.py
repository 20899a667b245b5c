"""A PS checkpoint from the resume file of a `playseg train` run that is still going: its best weights so far,
calibrated on the dataset's val split as `playseg train` calibrates, to segment and score with the CLI.

For a run longer than the time there is (the default budget on a busy CPU): the figures of the weights
the run would keep if it stopped now. The model is rebuilt as `playseg train` builds it with its default
options (bounds from the annotated segments, the domain's encoders, label head and end lookahead, the
previous action read); a run with other options needs them here too, and a state of another model is
refused by the weights' shapes.

    .venv/bin/python benchmarks/ps_checkpoint_from_state.py --state M.pt.train-state --data D --out SNAP.pt
    playseg segment --model SNAP.pt --input D --out SEG --splits test && playseg evaluate --pred SEG --truth D
"""

from __future__ import annotations

import argparse

import torch

from playseg_core.data.dataset import PlayDataset
from playseg_core.ps.calibration import LABEL_ACCURACY_TARGET, calibrate_ps_model
from playseg_core.ps.model import PSModel, save_model
from playseg_core.ps.training import model_config_for, segment_bounds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--state", required=True, help="the run's resume file (OUT.train-state)")
    parser.add_argument("--data", required=True, help="the dataset the run trains on")
    parser.add_argument("--out", required=True, help="checkpoint to write")
    parser.add_argument("--label-accuracy", type=float, default=LABEL_ACCURACY_TARGET)
    args = parser.parse_args()

    state = torch.load(args.state, weights_only=True, map_location="cpu")
    data = PlayDataset.open(args.data)
    train, val = list(data.episodes("train")), list(data.episodes("val"))
    bounds = segment_bounds(train, data.domain)
    config = model_config_for(
        data.features, data.domain, len(data.instructions), max_len=bounds.max_len, read_actions=True,
        episodes=train, min_len=bounds.min_len,
    )  # fmt: skip
    model = PSModel(config, list(data.instructions))
    model.load_state_dict(state["best_state"])
    model.eval()
    best = next((h for h in state["history"] if h["step"] == state["best_step"]), {})
    print(
        f"{args.state}: at step {state['step']}, best weights of step {state['best_step']} "
        f"(val_error {best.get('val_error', float('nan')):.4f}, val label accuracy on the true spans "
        f"{best.get('val_label_accuracy', float('nan')):.3f})"
    )
    calibrated = calibrate_ps_model(model, val, args.label_accuracy)
    record = f"best weights of step {state['best_step']} of {args.state}"
    save_model(args.out, model, {"trained_on": record, **calibrated})
    end = calibrated["end_bias"]
    print(
        f"{args.out}: calibrated on {len(val)} val episodes: end bias {end['bias']}, val exact F1 {end['f1']:.3f}"
    )


if __name__ == "__main__":
    main()
