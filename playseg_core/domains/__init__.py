"""Domains: everything one world knows, one package each (``playseg_core.domains.<name>``).

The generic machinery (data/, ps/, augment/, experiment/) never imports a domain package: it asks for a
`Domain` by the name a dataset, bag or checkpoint records (`load_domain`) and reads its fields. A domain
package builds its `Domain` once and registers it on import (`register_domain`), with its step
encoders (ps/encoders.py `register_encoder`). Loading a domain imports neither its simulator nor the
experiment framework: what needs them is reached through functions that import them when called.

A new robot's domain is a new package here (its ROS side, if any, is ``playseg_ros/<name>/``).
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from playseg_core.errors import PlaysegError
from playseg_core.registry import Registry

if TYPE_CHECKING:  # types only: the modules below import this one
    from playseg_core.augment.policy import PolicyLearner
    from playseg_core.data.features import Features
    from playseg_core.experiment.spec import ExperimentSpec
    from playseg_core.ps.encoders import EncoderSpec
    from playseg_core.ps.symmetries import ClipSymmetries


GenerateDataset = Callable[..., Any]
"""``generate_dataset(out, preset, seed=0, workers=1, progress=True, overwrite=False,
annotated_share=None)``: play of a named preset written as a dataset directory (`playseg generate`)."""


def preset_generator(module: str) -> GenerateDataset:
    """The `GenerateDataset` of a domain whose generator ``module`` (imported when called: it runs the
    world) has ``get_preset(name, annotated_share=...)`` and ``generate_dataset(out, preset, seed,
    workers, progress, overwrite)``."""

    def generate_dataset(
        out: str | Path,
        preset: str,
        seed: int = 0,
        workers: int = 1,
        progress: bool = True,
        overwrite: bool = False,
        annotated_share: float | None = None,
    ) -> Any:
        generate = importlib.import_module(module)
        chosen = generate.get_preset(preset, annotated_share=annotated_share)
        return generate.generate_dataset(out, chosen, seed, workers, progress, overwrite)

    return generate_dataset


@dataclass(frozen=True)
class Domain:
    """What one world contributes to the generic machinery; every field but ``name`` is optional.

    - ``step_encoders(features)``: its own step encoders for some features, by feature name (None: the
      feature is not read); the others get the generic ones (ps/encoders.py `choose_encoders`).
    - ``segment_bounds``: measured ``min_len``, ``max_len`` and ``k_max``, used instead of the bounds
      derived from the annotated segments (ps/training.py).
    - ``label_head``: the label head its PS and labelling models use (ps/model.py `LABEL_HEADS`).
    - ``end_lookahead``: steps past a candidate end its PS end head reads (ps/model.py
      `ModelConfig.end_lookahead`).
    - ``periodic_frequencies``: learnt frequencies of the periodic embeddings its PS and labelling
      models' trunk gives the measured observation values, and of the distances between measured
      positions (ps/model.py `TrunkConfig`); 0: neither, None: the generic default (ps/model.py
      `PERIODIC_FREQUENCIES`).
    - ``trunk_dropout``: the dropout of its PS and labelling models' trunk (ps/model.py `TrunkConfig`);
      None: the generic default (ps/model.py `TRUNK_DROPOUT`).
    - ``clip_symmetries``: the symmetries of its world, what ``playseg train --augment`` trains on
      (ps/symmetries.py); without them ``--augment`` turns camera frames only.
    - ``policies``: policy name -> factory (config -> `augment.policy.PolicyLearner`), each reached as
      ``<domain>.<policy>`` (augment/policies.py).
    - ``preset_names`` and ``generate_dataset``: the play it can generate (`playseg generate`).
    - ``experiment()``: its augmentation experiment (playseg_core/experiment), built when asked for.
    """

    name: str
    step_encoders: Callable[[Features], Mapping[str, EncoderSpec | None]] | None = None
    segment_bounds: Mapping[str, int] | None = None
    label_head: str = "linear"
    end_lookahead: int = 0
    periodic_frequencies: int | None = None
    trunk_dropout: float | None = None
    clip_symmetries: ClipSymmetries | None = None
    policies: Mapping[str, Callable[[dict[str, Any]], PolicyLearner]] = field(default_factory=dict)
    preset_names: tuple[str, ...] = ()
    generate_dataset: GenerateDataset | None = None
    experiment: Callable[[], ExperimentSpec] | None = None


DOMAINS: Registry[Domain] = Registry("domain")
"""The domains whose packages have been imported (`load_domain` imports one on first use)."""


_DOMAIN_NAME = re.compile(r"[a-z][a-z0-9_]*")
"""What a domain's name may be: a Python package name under playseg_core.domains."""


def register_domain(domain: Domain) -> Domain:
    """Make ``domain`` known by its name (a domain package calls this once, on import)."""
    return DOMAINS.register(domain.name, domain)


def has_domain_package(name: str) -> bool:
    """Whether ``name`` names a domain package (playseg_core.domains.<name>), found without importing it:
    a dataset's domain can be checked where its package's dependencies (torch) are not installed."""
    if not _DOMAIN_NAME.fullmatch(name or ""):
        return False
    return name in DOMAINS or importlib.util.find_spec(f"{__name__}.{name}") is not None


def load_domain(name: str) -> Domain:
    """The domain ``name``, its package imported on first use; PlaysegError naming it when there is none."""
    if not _DOMAIN_NAME.fullmatch(name or ""):
        raise PlaysegError(f"invalid domain name {name!r}")
    if name not in DOMAINS:
        try:
            importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as error:
            if error.name != f"{__name__}.{name}":
                raise
            raise PlaysegError(f"unknown domain {name!r} (no package playseg_core.domains.{name})") from None
    if name not in DOMAINS:
        raise PlaysegError(f"domain package playseg_core.domains.{name} registers no Domain")
    return DOMAINS[name]
