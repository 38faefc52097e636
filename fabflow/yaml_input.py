"""Reading YAML from users: bounded, with duplicate keys refused and a line for every node.

PyYAML's ``safe_load`` composes nested collections by recursion (``[`` nested
5,000 deep is a ``RecursionError``), keeps the last of two equal keys without a
word, and lets a few aliases stand for millions of nodes ("billion laughs").
:func:`parse_yaml` composes the document once with the nesting bounded, checks
the node tree (duplicate keys, the number of nodes counted through aliases,
recursive aliases, and, when asked, numbers that are not finite), then builds
the data from it. The result keeps the nodes, so that a problem found later
(a pydantic field path) can be given its line (:meth:`YamlDocument.line_of`).

Numbers follow YAML 1.2: ``1e-3`` is a number (PyYAML's YAML 1.1 reads it as
text). Files are read with :func:`fabflow.files.read_text` (regular, bounded, UTF-8).
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from fabflow.errors import InputError
from fabflow.files import read_text, show

MAX_DEPTH = 64
"""Deepest nesting of collections a document may have (a project file needs about 8)."""
MAX_NODES = 2_000_000
"""Most nodes a document may stand for, an alias counting as the nodes it repeats."""
MAX_YAML_BYTES = 4 * 2**20
"""Default bound of a YAML file (bytes): about 60,000 task points; a project is a few kB."""

_MERGE = "tag:yaml.org,2002:merge"
_YAML12_FLOAT = re.compile(
    r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$", re.ASCII
)
"""Exponent numbers without a dot (``1e-3``), floats in YAML 1.2 but text in YAML 1.1."""


class _TooDeepError(Exception):
    def __init__(self, mark: yaml.Mark) -> None:
        self.mark = mark


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader with the nesting of collections bounded."""

    def __init__(self, stream: str, max_depth: int) -> None:
        super().__init__(stream)
        self._depth = 0
        self._max_depth = max_depth

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        self._depth += 1
        try:
            if self._depth > self._max_depth:
                raise _TooDeepError(self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML12_FLOAT, list("-+0123456789."))


@dataclass(frozen=True)
class YamlDocument:
    """A parsed YAML document: the data and the nodes it was built from.

    Attributes
    ----------
    data
        The document as Python data (dicts, lists, scalars); ``None`` when empty.
    node
        The root node, or ``None`` for an empty document.
    source
        The file (or other source) named in errors.
    """

    data: Any
    node: yaml.Node | None
    source: str

    def line_of(self, loc: Sequence[Any]) -> int | None:
        """1-based line of the node at ``loc``; see :func:`line_of`."""
        return line_of(self.node, loc)


def line_of(node: yaml.Node | None, loc: Sequence[Any]) -> int | None:
    """1-based line of the node at ``loc`` (keys and list indices), or of its nearest parent.

    For a key the mapping does not have (an unknown key in a pydantic error), the
    line of the mapping.
    """
    line = None if node is None else node.start_mark.line + 1
    for part in loc:
        if isinstance(node, yaml.MappingNode):
            pair = next(
                ((k, v) for k, v in node.value if getattr(k, "value", None) == str(part)), None
            )
            if pair is None:
                return line
            node = pair[1]
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int):
            if not 0 <= part < len(node.value):
                return line
            node = node.value[part]
        else:
            return line
        line = node.start_mark.line + 1
    return line


def parse_yaml(
    text: str,
    source: str | Path = "<string>",
    *,
    finite: bool = False,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> YamlDocument:
    """Parse one YAML document safely (see the module docstring).

    Parameters
    ----------
    text
        The document.
    source
        The file, named in errors.
    finite
        Refuse floats that are not finite (``.nan``, ``.inf``, ``1e999``), naming the line.
    max_depth
        Deepest nesting of collections.
    max_nodes
        Most nodes, counted through aliases.

    Raises
    ------
    InputError
        YAML that does not parse, nests deeper than ``max_depth``, stands for
        more than ``max_nodes`` nodes, has a recursive alias, a duplicate key in
        a mapping, or (with ``finite``) a number that is not finite; the message
        names the line and quotes at most a short token.
    """
    try:
        loader = _Loader(text, max_depth)
    except yaml.reader.ReaderError as exc:
        line = text[: exc.position].count("\n") + 1
        raise InputError(
            f"YAML does not allow the character #x{exc.character:04x}", source, f"line {line}"
        ) from None
    try:
        node = loader.get_single_node()
        if node is not None:
            _check_nodes(node, loader, source, finite, max_nodes)
        data = None if node is None else loader.construct_document(node)
    except _TooDeepError as exc:
        raise InputError(
            f"collections nest deeper than {max_depth} levels", source, f"line {exc.mark.line + 1}"
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else None
        problem = str(getattr(exc, "problem", None) or "not valid YAML")
        if len(problem) > 120:  # it may quote the file (a tag, a key)
            problem = problem[:120] + "..."
        raise InputError(f"YAML does not parse: {problem}", source, where) from None
    finally:
        loader.dispose()
    return YamlDocument(data, node, str(source))


def read_yaml(
    path: str | Path,
    what: str = "YAML file",
    max_bytes: int = MAX_YAML_BYTES,
    *,
    finite: bool = False,
) -> YamlDocument:
    """Read and parse a YAML file (:func:`~fabflow.files.read_text`, then :func:`parse_yaml`)."""
    return parse_yaml(read_text(path, what, max_bytes), path, finite=finite)


def _check_nodes(
    root: yaml.Node, loader: _Loader, source: str | Path, finite: bool, max_nodes: int
) -> None:
    """Duplicate keys, node count through aliases, recursive aliases, non-finite floats."""
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_nodes:
            raise InputError("an alias refers to the collection it is in", source, _line(node))
        open_nodes.add(key)
        total = 1
        if isinstance(node, yaml.MappingNode):
            seen: dict[tuple[str, str], yaml.Node] = {}
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.tag != _MERGE:
                    first = seen.setdefault((k.tag, k.value), k)
                    if first is not k:
                        raise InputError(
                            f"duplicate key {show(k.value)} (first on {_line(first)})",
                            source,
                            _line(k),
                        )
                total += size(k) + size(v)
        elif isinstance(node, yaml.SequenceNode):
            total += sum(size(v) for v in node.value)
        else:
            _check_scalar(node, loader, source, finite)
        if total > max_nodes:
            raise InputError(
                f"the document stands for more than {max_nodes} values (through aliases)",
                source,
                _line(node),
            )
        open_nodes.discard(key)
        sizes[key] = total
        return total

    size(root)


def _check_scalar(node: yaml.Node, loader: _Loader, source: str | Path, finite: bool) -> None:
    """Build a scalar now, so that a bad one (``!!int abc``, a 5,000-digit number) has its line."""
    if node.tag == _MERGE:
        return
    try:
        value = loader.construct_object(node)
    except (ValueError, TypeError, OverflowError):
        kind = str(node.tag).rsplit(":", 1)[-1]
        raise InputError(f"{show(node.value)} is not a valid {kind}", source, _line(node)) from None
    if not finite or isinstance(value, bool) or not isinstance(value, int | float):
        return
    if not math.isfinite(value) if isinstance(value, float) else abs(value) > sys.float_info.max:
        raise InputError(f"{show(node.value)} is not a finite number", source, _line(node))


def _line(node: yaml.Node) -> str:
    return f"line {node.start_mark.line + 1}"
