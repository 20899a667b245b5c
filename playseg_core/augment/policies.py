"""The policies by name: a generic one for any domain's data (``GENERIC_POLICIES``, named without a dot,
e.g. ``bc``) or one of a domain (its `Domain.policies`, named ``<domain>.<policy>``); `load_policy_learner` builds the `PolicyLearner` a name stands for.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from playseg_core.augment.bc_policy import BCPolicyLearner
from playseg_core.augment.policy import PolicyLearner
from playseg_core.data.features import Features
from playseg_core.domains import load_domain
from playseg_core.errors import PlaysegError
from playseg_core.registry import Registry

GenericPolicy = Callable[[dict[str, Any], Features | None], PolicyLearner]

GENERIC_POLICIES: Registry[GenericPolicy] = Registry("generic policy")
"""Policies for any domain's data, by name: factory (config, the data's features) -> learner."""


@GENERIC_POLICIES.add("bc")
def _bc_policy(config: dict[str, Any], features: Features | None) -> PolicyLearner:
    return BCPolicyLearner.from_config(config, features)


def load_policy_learner(
    name: str, config: Mapping[str, Any] | None = None, features: Features | None = None
) -> PolicyLearner:
    """The learner ``name`` built from ``config``: a generic policy (a name without a dot, built for data
    with ``features``) or ``<domain>.<policy>`` (a domain's policy, which knows its own features and
    ignores ``features``); PlaysegError naming what is unknown."""
    domain, _, policy = name.partition(".")
    if not policy:
        if name not in GENERIC_POLICIES:
            raise PlaysegError(
                f"policy {name!r}: not a generic policy ({sorted(GENERIC_POLICIES)}) nor <domain>.<policy>"
            )
        return GENERIC_POLICIES[name](dict(config or {}), features)
    policies = load_domain(domain).policies
    if policy not in policies:
        raise PlaysegError(f"policy {name!r}: domain {domain!r} has {sorted(policies) or 'no policies'}")
    return policies[policy](dict(config or {}))
