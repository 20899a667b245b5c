"""One way to make things findable by name: segmentation methods (baselines/registry.py), step encoders
(ps/encoders.py), generic policies (augment/policies.py) and domains (playseg_core/domains).

A `Registry` holds the things of one kind, each registered once under its name; asking for a name it
does not hold is a one-line `PlaysegError` that lists the names it does.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from playseg_core.errors import PlaysegError

T = TypeVar("T")


class Registry(Generic[T]):
    """Things of one ``kind`` (e.g. "segmentation method") by name, in the order they were registered."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._items: dict[str, T] = {}

    def register(self, name: str, item: T) -> T:
        """Hold ``item`` under ``name``; registering the same item again is a no-op, another one an error."""
        known = self._items.get(name)
        if known is not None and known is not item:
            raise PlaysegError(f"{self.kind} {name!r} is registered twice")
        self._items[name] = item
        return item

    def add(self, name: str) -> Callable[[T], T]:
        """`register` as a decorator: ``@REGISTRY.add("name")``."""
        return lambda item: self.register(name, item)

    def __getitem__(self, name: str) -> T:
        if name not in self._items:
            raise PlaysegError(f"unknown {self.kind} {name!r} (known: {', '.join(self._items) or 'none'})")
        return self._items[name]

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def values(self) -> list[T]:
        return list(self._items.values())
