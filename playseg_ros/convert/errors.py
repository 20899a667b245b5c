"""The exceptions of `playseg convert`: one for the mapping file, one for a bag. Both print as one line."""

from __future__ import annotations

from pathlib import Path

from playseg_core.errors import PlaysegError


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


class MappingError(PlaysegError):
    """A mapping file that cannot be used; the message names the file and the key (``features.action.topic``)."""

    def __init__(self, mapping: Path | str, key: str | None, detail: str, what: str = "mapping") -> None:
        self.mapping, self.key, self.detail = Path(mapping), key, _one_line(detail)
        where = f"{what} {str(mapping)!r}" + (f", key {key!r}" if key else "")
        super().__init__(f"{where}: {self.detail}")


class ConvertError(PlaysegError):
    """A bag that cannot be converted with its mapping; the message names the bag and, where known, the
    topic, field and message time (seconds since the epoch)."""

    def __init__(
        self,
        bag: Path | str,
        detail: str,
        topic: str | None = None,
        field: str | None = None,
        time_ns: int | None = None,
    ) -> None:
        self.bag, self.topic, self.field, self.time_ns = Path(bag), topic, field, time_ns
        self.detail = _one_line(detail)
        where = [f"bag {str(bag)!r}"]
        if topic is not None:
            where.append(f"topic {topic!r}")
        if field is not None:
            where.append(f"field {field!r}")
        if time_ns is not None:
            where.append(f"time {time_ns / 1e9:.6f}")
        super().__init__(f"{', '.join(where)}: {self.detail}")
