"""The one exception of bag I/O."""

from __future__ import annotations

from pathlib import Path


class BagError(ValueError):
    """A bag that cannot be read or written as asked; the message names where (bag, topic, episode, step)."""

    def __init__(
        self,
        bag: Path | str,
        detail: str,
        topic: str | None = None,
        episode: str | None = None,
        step: int | None = None,
    ) -> None:
        self.bag, self.topic, self.episode, self.step, self.detail = Path(bag), topic, episode, step, detail
        where = [f"bag {str(bag)!r}"]
        if topic is not None:
            where.append(f"topic {topic!r}")
        if episode is not None:
            where.append(f"episode {episode!r}")
        if step is not None:
            where.append(f"step {step}")
        super().__init__(f"{', '.join(where)}: {detail}")
