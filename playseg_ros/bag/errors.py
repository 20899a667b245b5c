"""The one exception of bag I/O."""

from __future__ import annotations

from pathlib import Path

from playseg_core.errors import PlaysegError


class BagError(PlaysegError):
    """A bag that cannot be read or written as asked; the message names where (bag, file, topic, episode,
    step) on one line."""

    def __init__(
        self,
        bag: Path | str,
        detail: str,
        topic: str | None = None,
        episode: str | None = None,
        step: int | None = None,
        *,
        file: str | None = None,
    ) -> None:
        self.bag, self.topic, self.episode, self.step = Path(bag), topic, episode, step
        self.file = file
        # Library errors (zstd, yaml, sqlite) may span lines; a BagError is one line in a log.
        self.detail = " ".join(str(detail).split())
        where = [f"bag {str(bag)!r}"]
        if file is not None:
            where.append(f"file {file!r}")
        if topic is not None:
            where.append(f"topic {topic!r}")
        if episode is not None:
            where.append(f"episode {episode!r}")
        if step is not None:
            where.append(f"step {step}")
        super().__init__(f"{', '.join(where)}: {self.detail}")
