"""The one YAML loader for every file the project reads (mappings, annotation sidecars, graph configs,
bag metadata): safe tags only, with limits, and errors that name the file and the entry.

Plain ``yaml.safe_load`` has three ways to hang or crash on a small hostile file, each closed here:

- *alias expansion* ("billion laughs"): anchors and aliases share nodes, so a 1 KB file can describe
  10^9 values; any walk over the result (a digest, a duplicate-key check, an error message) then runs
  for minutes. The composed node graph is measured once with memoisation and refused when it would
  expand past ``max_values``; an alias that contains itself is refused too.
- *nesting*: PyYAML composes recursively, so ``[[[[...]]]]`` a few thousand deep is a RecursionError.
  Composition stops at ``max_depth`` levels (counted through aliases as well).
- *size*: a file over ``max_bytes`` is not read at all.

A key given twice in one mapping (plain YAML keeps the last silently) is an error naming both lines.
Messages never quote the file's content beyond a short key path (a path given by mistake may point at
a file that should not be echoed into a log): a syntax error is located by line and column.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from playseg_core.errors import PlaysegError

__all__ = ["YamlFileError", "YamlLimits", "load_yaml", "parse_yaml"]


@dataclass(frozen=True)
class YamlLimits:
    """What a YAML file may hold; far above any real mapping, sidecar, graph config or metadata.yaml."""

    max_bytes: int = 16 * 1024 * 1024
    max_depth: int = 64
    max_values: int = 2_000_000
    """Scalars, sequences and mappings after every alias is expanded."""


DEFAULT_LIMITS = YamlLimits()


class YamlFileError(PlaysegError):
    """A YAML file that cannot be used: ``<what> '<path>'[, key '<entry>']: <detail>``, one line."""

    def __init__(self, path: Path | str, key: str | None, detail: str, what: str = "YAML file") -> None:
        self.path, self.key, self.what = Path(path), key, what
        self.detail = " ".join(str(detail).split())
        where = f"{what} {str(path)!r}" + (f", key {key!r}" if key else "")
        super().__init__(f"{where}: {self.detail}")


def load_yaml(path: Path | str, what: str = "YAML file", limits: YamlLimits = DEFAULT_LIMITS) -> Any:
    """The content of the YAML (or JSON) file ``path``; `YamlFileError` naming the file (and the entry,
    where there is one) when it cannot be read, is not UTF-8 YAML, or breaks ``limits``."""
    path = Path(path)
    if path.is_dir():
        raise YamlFileError(path, None, "is a directory, not a file", what)
    try:
        with path.open("rb") as file:  # read at most one byte past the limit: a FIFO or /dev/zero ends too
            data = file.read(limits.max_bytes + 1)
    except OSError as error:
        raise YamlFileError(path, None, f"cannot read: {error.strerror or error}", what) from None
    if len(data) > limits.max_bytes:
        raise YamlFileError(path, None, f"larger than {limits.max_bytes} bytes; refusing to read it", what)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise YamlFileError(
            path,
            None,
            f"not UTF-8 text (byte {data[error.start]:#04x} at offset {error.start}): a binary file?",
            what,
        ) from None
    return parse_yaml(text, path, what, limits)


def parse_yaml(
    text: str, path: Path | str, what: str = "YAML file", limits: YamlLimits = DEFAULT_LIMITS
) -> Any:
    """``text`` (the content of ``path``, or of a record inside it) as Python values, under ``limits``."""
    if len(text) > limits.max_bytes:
        raise YamlFileError(
            path, None, f"larger than {limits.max_bytes} characters; refusing to parse it", what
        )
    loader: _Loader | None = None
    try:
        loader = _Loader(text, limits.max_depth)  # its reader refuses control characters here
        try:
            node = loader.get_single_node()
        except _TooDeep as deep:
            raise YamlFileError(
                path, None, f"nested deeper than {limits.max_depth} levels (line {deep.line})", what
            ) from None
        if node is None:
            return None
        _check(node, path, what, limits)
        try:
            return loader.construct_document(node)
        except yaml.YAMLError:
            raise
        except Exception as error:  # noqa: BLE001 -- the safe constructors fail in many ways on odd scalars
            raise _unreadable_value(error, path, what) from None
    except YamlFileError:
        raise
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        at = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        problem = _without_content(
            ": ".join(filter(None, (error.context, error.problem))) or type(error).__name__
        )
        raise YamlFileError(path, None, f"not valid YAML{at}: {problem}", what) from None
    except yaml.reader.ReaderError as error:
        raise YamlFileError(
            path,
            None,
            f"not YAML text: character U+{error.character:04X} at offset {error.position} is not allowed",
            what,
        ) from None
    except yaml.YAMLError as error:
        raise YamlFileError(path, None, f"not valid YAML: {_without_content(str(error))}", what) from None
    finally:
        if loader is not None:
            loader.dispose()


def _unreadable_value(error: Exception, path: Path | str, what: str) -> YamlFileError:
    """A scalar the safe constructor cannot make: 2024-13-45 (ValueError), ``!!float ''`` (IndexError in
    PyYAML), a 5000-digit integer."""
    detail = str(error) if isinstance(error, ValueError | OverflowError) else type(error).__name__
    if "integer string conversion" in detail:  # Python's own message asks for an interpreter setting
        detail = "a whole number of more than 4300 digits"
    return YamlFileError(path, None, f"a value cannot be read: {_without_content(detail)}", what)


class _TooDeep(Exception):
    def __init__(self, line: int) -> None:
        self.line = line


class _Loader(yaml.SafeLoader):
    """SafeLoader (pure Python: its composer is the one we can bound) that stops composing past a depth."""

    def __init__(self, text: str, max_depth: int) -> None:
        super().__init__(text)
        self._depth, self._max_depth = 0, max_depth

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        self._depth += 1
        try:
            if self._depth > self._max_depth:
                raise _TooDeep(self.peek_event().start_mark.line + 1)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _check(root: yaml.Node, path: Path | str, what: str, limits: YamlLimits) -> None:
    """Refuse a node graph that expands past the limits, holds a cycle, or gives a key twice. Each node is
    measured once (memoised), so shared aliases cost nothing."""
    measured: dict[int, tuple[int, int]] = {}  # id(node) -> (values after expansion, height)
    open_nodes: set[int] = set()

    def fail(key: str, detail: str) -> YamlFileError:
        return YamlFileError(path, key or None, detail, what)

    def measure(node: yaml.Node, level: int, key: str) -> tuple[int, int]:
        known = measured.get(id(node))
        if known is not None:
            if level + known[1] > limits.max_depth:
                raise fail(
                    key, f"nested deeper than {limits.max_depth} levels through aliases (line {_line(node)})"
                )
            return known
        if id(node) in open_nodes:
            raise fail(key, f"an alias refers to a node that contains it (line {_line(node)})")
        if level >= limits.max_depth:
            raise fail(
                key, f"nested deeper than {limits.max_depth} levels through aliases (line {_line(node)})"
            )
        open_nodes.add(id(node))
        size, height = 1, 0
        if isinstance(node, yaml.MappingNode):
            seen: dict[str, int] = {}
            for key_node, value_node in node.value:
                name = str(key_node.value) if isinstance(key_node, yaml.ScalarNode) else "?"
                if isinstance(key_node, yaml.ScalarNode) and name != "<<":
                    if name in seen:
                        raise fail(
                            _join(key, name), f"given twice (lines {seen[name]} and {_line(key_node)})"
                        )
                    seen[name] = _line(key_node)
                for child, child_key in ((key_node, key), (value_node, _join(key, name))):
                    child_size, child_height = measure(child, level + 1, child_key)
                    size, height = size + child_size, max(height, child_height + 1)
                    if size > limits.max_values:
                        break
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                item_size, item_height = measure(item, level + 1, f"{key}[{i}]")
                size, height = size + item_size, max(height, item_height + 1)
                if size > limits.max_values:
                    break
        if size > limits.max_values:
            raise fail(
                key,
                f"its aliases expand to more than {limits.max_values} values (line {_line(node)}); refusing "
                "it (an alias bomb?)",
            )
        open_nodes.discard(id(node))
        measured[id(node)] = (size, height)
        return size, height

    measure(root, 0, "")


def _join(prefix: str, name: str) -> str:
    name = name if len(name) <= 60 else name[:57] + "..."  # a key is quoted, but never a whole line
    return f"{prefix}.{name}" if prefix else name


def _line(node: yaml.Node) -> int:
    return node.start_mark.line + 1


_QUOTED = re.compile(r"""(['"])(.{4,}?)\1""")


def _without_content(text: str) -> str:
    """A library message without the file's text: PyYAML quotes tags, anchors and values it refuses;
    short quotes (a ':' or a tab it expected or found) stay."""
    return _QUOTED.sub("(...)", " ".join(text.split()))
