"""Formation files from bytes to a YAML document whose every node has its ``FILE:LINE:COL``.

The one reader of formation files (:func:`read_document`, :func:`parse_document`):

- at most :data:`MAX_BYTES`; UTF-8 text only (a PNG or a bag given by mistake is one line of
  error naming the first bad byte, not a traceback);
- YAML aliases may repeat a node, but the document they expand to may hold at most
  :data:`ALIAS_BUDGET` nodes, counted on the composed graph before anything is constructed:
  an alias bomb is refused in bounded time and memory; recursive aliases are refused;
- a key given twice in one mapping is an error naming both lines (YAML would keep the last);
  raised, or kept in :attr:`Document.errors` (``collect_duplicates``) with the first value read so
  that the rest of the file can still be checked;
- numbers in exponent form without a dot (``1e4``) are floats, as in YAML 1.2 (PyYAML's YAML
  1.1 reads them as strings);
- :class:`Document` maps every field path (``agents[0].controller.gamma``) to its position,
  so that :func:`locate` can give each :class:`FormationSpecError` its ``FILE:LINE:COL`` and put
  the errors of a file in file order.
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from formation_core.errors import FormationSpecError, each_error, one_error

#: No formation file comes near this (a 50-agent file is ~40 kB).
MAX_BYTES = 4_000_000
#: Nodes the document may hold once every alias is expanded (a 50-agent file holds ~5 000).
ALIAS_BUDGET = 100_000

PathKey = tuple[Any, ...]


if TYPE_CHECKING:
    _SafeLoader = yaml.SafeLoader  # what the checker sees: the pure-Python loader, the same interface
else:
    _SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _Loader(_SafeLoader):
    """SafeLoader that reads ``1e4`` as a float (YAML 1.2), on its own copy of the resolvers.

    libyaml's parser where PyYAML has it (the wheels do): it composes a 50-agent file in 17 ms
    instead of 190 ms (every agent process loads the whole file); tags are still resolved here.
    """


_Loader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


@dataclass
class Document:
    """A parsed formation file: the plain data and the position of every node, by field path.

    ``errors``: the duplicate keys, when parsed with ``collect_duplicates`` (``data`` holds the
    first value of each)."""

    data: Any
    source: str
    positions: dict[PathKey, tuple[int, int]]
    errors: list[FormationSpecError] = field(default_factory=list)

    def location(self, path: str) -> str:
        """``FILE:LINE:COL`` of the node at ``path``, or of its nearest enclosing node."""
        key = split_path(path)
        while key not in self.positions and key:
            key = key[:-1]
        line, col = self.positions.get(key, (1, 1))
        return f"{self.source}:{line}:{col}"


_PATH_PART = re.compile(r"([^.\[\]]+)|\[(\d+)\]")


def split_path(path: str) -> PathKey:
    """``agents[0].controller.gamma`` -> ("agents", 0, "controller", "gamma")."""
    return tuple(int(i) if i else name for name, i in _PATH_PART.findall(path))


def _error(source: str, mark: Any, path: str, message: str) -> FormationSpecError:
    err = FormationSpecError(path, message)
    if mark is not None:
        err.location = f"{source}:{mark.line + 1}:{mark.column + 1}"
    else:
        err.location = source
    return err


def _check_graph(root: yaml.Node, source: str) -> None:
    """Refuse recursive aliases and a document expanding beyond ALIAS_BUDGET nodes."""
    size: dict[int, int] = {}
    active: set[int] = set()

    def count(node: yaml.Node) -> int:
        key = id(node)
        if key in size:
            return size[key]
        if key in active:
            raise _error(source, node.start_mark, "", "a YAML alias refers to a node that contains it (recursive)")
        active.add(key)
        n = 1
        if isinstance(node, yaml.SequenceNode):
            n += sum(count(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            n += sum(count(k) + count(v) for k, v in node.value)
        active.discard(key)
        size[key] = min(n, ALIAS_BUDGET + 1)  # saturate: the sum stays a small integer
        return size[key]

    total = count(root)
    if total > ALIAS_BUDGET:
        # name the outermost node whose own expansion already exceeds the budget
        node = root
        while True:
            children = (
                node.value
                if isinstance(node, yaml.SequenceNode)
                else [v for _, v in node.value]
                if isinstance(node, yaml.MappingNode)
                else []
            )
            big = next((c for c in children if size.get(id(c), 0) > ALIAS_BUDGET), None)
            if big is None:
                break
            node = big
        raise _error(
            source,
            node.start_mark,
            "",
            f"YAML aliases expand this document beyond {ALIAS_BUDGET} nodes (an alias bomb?): write the values out",
        )


def _index(root: yaml.Node, source: str) -> tuple[dict[PathKey, tuple[int, int]], list[FormationSpecError]]:
    """Positions of every node by path, and the duplicate keys (each error names both lines).

    A duplicate key is removed from its mapping node: the document built from it keeps the first
    value, the one whose position is indexed (errors about it then point at the right line)."""
    positions: dict[PathKey, tuple[int, int]] = {}
    errors: list[FormationSpecError] = []

    def walk(node: yaml.Node, path: PathKey, mark: Any = None) -> None:
        """``mark``: where the node's key is (an error about a field points at its key)."""
        mark = mark or node.start_mark
        positions.setdefault(path, (mark.line + 1, mark.column + 1))
        if isinstance(node, yaml.SequenceNode):
            for i, child in enumerate(node.value):
                walk(child, (*path, i))
        elif isinstance(node, yaml.MappingNode):
            seen: dict[Any, yaml.Node] = {}
            merged: list[yaml.Node] = []
            kept: list[tuple[yaml.Node, yaml.Node]] = []
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.tag == "tag:yaml.org,2002:merge":
                    merged.extend(v.value if isinstance(v, yaml.SequenceNode) else [v])
                    kept.append((k, v))
                    continue
                name = k.value if isinstance(k, yaml.ScalarNode) else id(k)
                if name in seen:
                    where = _format_path((*path, name))
                    errors.append(
                        _error(
                            source,
                            k.start_mark,
                            where,
                            f"duplicate key (first at line {seen[name].start_mark.line + 1}); "
                            "YAML would silently keep the last one",
                        )
                    )
                    continue
                seen[name] = k
                kept.append((k, v))
                walk(v, (*path, name), k.start_mark)
            node.value = kept
            for m in merged:  # merge keys (<<: *defaults) add only keys not given here
                if isinstance(m, yaml.MappingNode):
                    for k, v in m.value:
                        if isinstance(k, yaml.ScalarNode) and k.value not in seen:
                            walk(v, (*path, k.value), k.start_mark)

    walk(root, ())
    return positions, errors


def _format_path(key: PathKey) -> str:
    out = ""
    for part in key:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def parse_document(raw: bytes, source: str, *, size: int | None = None, collect_duplicates: bool = False) -> Document:
    """Bytes of a formation file -> :class:`Document`; raises FormationSpecError(s) with FILE:LINE:COL.

    ``size``: the file's size [bytes] when ``raw`` holds only its first :data:`MAX_BYTES` + 1.
    ``collect_duplicates``: duplicate keys go to :attr:`Document.errors` instead of being raised."""
    if len(raw) > MAX_BYTES:
        whole = f"{size} bytes" if size is not None and size >= len(raw) else f"more than {MAX_BYTES} bytes"
        raise _error(source, None, "", f"{whole} is more than any formation file (limit {MAX_BYTES} bytes)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        col = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        err = FormationSpecError("", f"not UTF-8 text (byte 0x{raw[exc.start]:02x}): a formation file is YAML text")
        err.location = f"{source}:{line}:{col}"
        raise err from None
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
        if root is None:
            raise _error(source, None, "", "the file is empty: a formation file is a mapping (agents, edges, …)")
        _check_graph(root, source)
        positions, duplicates = _index(root, source)
        if duplicates and not collect_duplicates:
            raise one_error(duplicates)
        data = loader.construct_document(root)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        raise _error(source, mark, "", f"not valid YAML: {problem}") from None
    except RecursionError:
        raise _error(source, None, "", "YAML nesting too deep") from None
    finally:
        loader.dispose()
    return Document(data, source, positions, duplicates)


def read_document(path: str | Path, *, collect_duplicates: bool = False) -> Document:
    """Read and parse a formation file (see :func:`parse_document`)."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            info = os.fstat(fh.fileno())
            size = info.st_size if stat.S_ISREG(info.st_mode) else None  # a pipe has no size
            raw = fh.read(MAX_BYTES + 1)  # no more: a 100 GB file given by mistake is not read
    except FileNotFoundError:
        raise FormationSpecError("", f"formation file {str(path)!r} does not exist", str(path)) from None
    except IsADirectoryError:
        raise FormationSpecError("", f"{str(path)!r} is a directory, not a formation file", str(path)) from None
    except OSError as exc:
        raise FormationSpecError("", f"cannot read {str(path)!r}: {exc.strerror}", str(path)) from None
    return parse_document(raw, str(path), size=size, collect_duplicates=collect_duplicates)


_LINE_COL = re.compile(r":(\d+):(\d+)$")


def _file_order(error: FormationSpecError) -> tuple[int, int]:
    """(line, column) of a located error; (0, 0), first, for one about the whole file."""
    found = _LINE_COL.search(error.location)
    return (int(found[1]), int(found[2])) if found else (0, 0)


def locate(errors: Iterable[FormationSpecError], document: Document) -> FormationSpecError:
    """``errors`` (each, or each of several) with its FILE:LINE:COL from ``document`` (kept if already
    set), as one exception, in file order (errors at one position stay in the order given)."""
    flat = [e for error in errors for e in each_error(error)]
    for e in flat:
        if not e.location:
            e.location = document.location(e.path)
        for element in e.elements:
            element[2] = element[2] or document.location(element[1])
    return one_error(sorted(flat, key=_file_order))
