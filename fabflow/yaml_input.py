"""Reading YAML that a user wrote: bounded, unambiguous, with the line of every node.

:func:`read_yaml` and :func:`parse_yaml` load one YAML document (a project
file, an anchors file) with PyYAML's safe loader and refuse what a plain
``yaml.safe_load`` lets through:

- a file over :data:`MAX_YAML_BYTES` (read through :func:`fabflow.files.read_text`,
  so devices, pipes and non-UTF-8 text are refused there);
- collections nested deeper than :data:`MAX_YAML_DEPTH` (``[`` nested 5,000 deep
  would exhaust the interpreter's stack);
- aliases that expand to more than :data:`MAX_YAML_NODES` nodes (a "billion
  laughs" file) or that contain themselves;
- a key written twice in one mapping (PyYAML keeps the last one silently).

Numbers follow YAML 1.2: ``1e-3`` is a number (PyYAML's YAML 1.1 reads it as
text). Every problem is an :class:`~fabflow.errors.InputError` naming the file
and the line; the document's node tree is returned with the data so that later
messages can name the line of a field (:func:`line_of`).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from fabflow.errors import InputError
from fabflow.files import read_text, show

MAX_YAML_BYTES = 4 * 2**20
"""Largest YAML file read (bytes): about 60,000 task points; a project is a few kB."""
MAX_YAML_DEPTH = 64
"""Deepest nesting of collections; the project schema needs fewer than 10 levels."""
MAX_YAML_NODES = 2_000_000
"""Most nodes a document may hold with its aliases expanded."""

_YAML12_FLOAT = re.compile(
    r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$", re.ASCII
)
"""Exponent numbers without a dot (``1e-3``), floats in YAML 1.2 but text in YAML 1.1."""


_MERGE = "tag:yaml.org,2002:merge"


class _Loader(yaml.SafeLoader):
    """The safe loader with a depth bound, no duplicate keys and YAML 1.2 exponents."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                mark = self.peek_event().start_mark
                raise yaml.MarkedYAMLError(
                    problem=f"collections are nested more than {MAX_YAML_DEPTH} deep",
                    problem_mark=mark,
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def compose_mapping_node(self, anchor: str | None) -> yaml.MappingNode:
        node = super().compose_mapping_node(anchor)
        seen: dict[tuple[str, str], yaml.Node] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE:
                continue
            key = (key_node.tag, key_node.value)
            if key in seen:
                first = seen[key].start_mark.line + 1
                raise yaml.MarkedYAMLError(
                    problem=f"duplicate key {show(key_node.value)} (first given on line {first})",
                    problem_mark=key_node.start_mark,
                )
            seen[key] = key_node
        return node


_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _YAML12_FLOAT, list("-+0123456789."))


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def _check_expansion(root: yaml.Node) -> None:
    """Refuse aliases that expand beyond :data:`MAX_YAML_NODES` nodes or into themselves.

    Iterative depth-first count over the node graph, each shared node counted once
    per reference (linear in the number of distinct nodes).
    """
    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            on_path.discard(key)
            size[key] = 1 + sum(size[id(c)] for c in _children(node))
            if size[key] > MAX_YAML_NODES:
                raise yaml.MarkedYAMLError(
                    problem=f"with its aliases expanded the document has more than "
                    f"{MAX_YAML_NODES:,} nodes",
                    problem_mark=node.start_mark,
                )
            continue
        if key in size:
            continue
        if key in on_path:
            raise yaml.MarkedYAMLError(
                problem="an alias refers to a collection that contains it",
                problem_mark=node.start_mark,
            )
        on_path.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node) if id(c) not in size)


def _problem(exc: yaml.YAMLError) -> str:
    """What PyYAML found wrong, with its context, without quoting the text."""
    problem = getattr(exc, "problem", None) or type(exc).__name__
    context = getattr(exc, "context", None)
    if context:
        mark = getattr(exc, "context_mark", None)
        problem = f"{problem}: {context}" + (f" on line {mark.line + 1}" if mark else "")
    return problem if len(problem) <= 200 else problem[:200] + "..."


def parse_yaml(text: str, source: str | Path = "<string>") -> tuple[yaml.Node | None, Any]:
    """The node tree and the data of one YAML document.

    Parameters
    ----------
    text
        The YAML text.
    source
        The file it came from, named in messages.

    Returns
    -------
    node, data
        The composed node tree (``None`` for an empty document) and the Python data.

    Raises
    ------
    InputError
        YAML that does not parse, nests too deep, expands too far or repeats a
        key; names the line and column.
    """
    try:
        loader = _Loader(text)
    except yaml.reader.ReaderError as exc:
        line = text[: exc.position].count("\n") + 1
        raise InputError(
            f"YAML does not parse: the character #x{exc.character:04x} is not allowed",
            source,
            f"line {line}",
        ) from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None, None
        _check_expansion(node)
        data = loader.construct_document(node)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else None
        raise InputError(f"YAML does not parse: {_problem(exc)}", source, where) from None
    finally:
        loader.dispose()
    return node, data


def read_yaml(path: str | Path, what: str = "YAML file") -> tuple[yaml.Node | None, Any]:
    """:func:`parse_yaml` of a file of at most :data:`MAX_YAML_BYTES` (UTF-8, regular).

    Raises
    ------
    InputError
        As :func:`fabflow.files.read_text` and :func:`parse_yaml`.
    """
    return parse_yaml(read_text(path, what, MAX_YAML_BYTES), path)


def line_of(node: yaml.Node | None, loc: tuple[Any, ...]) -> int | None:
    """1-based line of the value at ``loc`` (keys and indices), or of its nearest parent."""
    line = None if node is None else node.start_mark.line + 1
    for part in loc:
        if isinstance(node, yaml.MappingNode):
            pair = next((kv for kv in node.value if getattr(kv[0], "value", None) == part), None)
            if pair is None:
                return line
            node = pair[1]
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int):
            if part >= len(node.value):
                return line
            node = node.value[part]
        else:
            return line
        line = node.start_mark.line + 1
    return line
