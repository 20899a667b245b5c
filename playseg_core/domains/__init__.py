"""Domains: everything one world knows, one package each (``playseg_core.domains.<name>``).

The generic machinery (data/, ps/, augment/) never imports a domain package; it asks for one by name,
the name a dataset, bag or checkpoint records (`load_domain`). On import, a domain package registers its
step encoders (ps/encoders.py) and exposes:

- optionally ``step_encoders(features) -> {feature name: EncoderSpec | None}``: its own step encoders
  for some features (None: not read); the others get the generic ones (ps/encoders.py);
- optionally ``SEGMENT_BOUNDS`` (``min_len``, ``max_len``, ``k_max``): its measured segment-length
  bounds, used instead of the ones derived from the annotated segments (ps/training.py);
- optionally ``LABEL_HEAD``: the label head its PS and labelling models use by default ("linear" or
  "text", ps/model.py `LABEL_HEADS`);
- optionally ``END_LOOKAHEAD``: how many steps past a candidate end its PS end head reads by default
  (ps/model.py `ModelConfig.end_lookahead`; 0, the paper's model, otherwise);
- optionally ``END_GROUNDING``: the attention heads of its PS end head's grounded part by default
  (ps/model.py `GroundedEndHead`; 0, none, otherwise);
- optionally ``CLIP_SYMMETRIES``: the symmetries of its world (ps/samples.py `ClipSymmetries`: how
  many, and how each turns a training clip as recorded and its instruction), what `playseg train
  --augment` trains on; without them, ``--augment`` turns the camera frames only, for models that read
  no actions;
- ``POLICIES``: policy name -> factory of an `augment.policy.PolicyLearner` (config dict -> learner);
- optionally ``PRESET_NAMES`` and ``generate_dataset(out, preset, seed, workers, progress, overwrite,
  annotated_share)`` when it can generate play (`playseg generate --domain <name>`).

A new robot's domain is a new package here.
"""

from __future__ import annotations

import importlib
import re
from types import ModuleType

from playseg_core.errors import PlaysegError


def load_domain(name: str) -> ModuleType:
    """The domain package ``name``; ValueError naming it when there is none."""
    if not re.fullmatch(r"[a-z][a-z0-9_]*", name or ""):
        raise PlaysegError(f"invalid domain name {name!r}")
    try:
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as error:
        if error.name != f"{__name__}.{name}":
            raise
        raise PlaysegError(f"unknown domain {name!r} (no package playseg_core.domains.{name})") from None
