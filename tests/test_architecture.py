"""The import graph of src/: no circles, imports pointing one way, ROS only in the nodes.

Every module under ``src/`` is parsed (not imported); each ``formation_*`` import is an edge:
absolute or relative (``from . import x`` resolved against the module's package), by ``importlib``
(``import_module`` or ``__import__`` of a literal name), function-level (lazy) imports included: a
lazy import still ties two modules together. A module name computed at run time is refused unless
:data:`DYNAMIC_IMPORTS` says what it can load. The
packages, from the bottom: ``formation_core`` (ROS-free: the formation file, options, verdicts,
numerics) -> ``formation_msgs_py`` (topics, codec, QoS, conversions) -> ``formation_ros`` (the nodes'
rclpy plumbing) -> ``formation_deploy`` (security, deployment) -> ``formation_agent`` ->
``formation_bag`` (bag I/O, the record and replay nodes, the live Foxglove server) -> ``formation_sim``.
Inside formation_sim: ``cli`` -> ``launch`` | ``node`` | ``offline`` -> ``preflight`` -> ``core``; ``views``
serve the runners and the analysis; ROS (rclpy, message packages) only in the nodes.
"""

from __future__ import annotations

import ast
import functools
import itertools
from dataclasses import dataclass
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

#: Top-level names of ROS 2 client libraries; any ``*_msgs`` package counts as ROS too.
_ROS_TOP = {"rclpy", "builtin_interfaces", "rosidl_runtime_py", "rmw", "launch", "launch_ros"}

#: The only modules that may import ROS (rclpy or message packages): the messages' QoS and conversions, the
#: nodes' rclpy plumbing (with the parameter tool), the simulator node's folder, the three other nodes and the
#: graph watch of the intruder detection.
ROS_ALLOWED_PACKAGES = ("formation_msgs_py.ros", "formation_ros", "formation_sim.node")
ROS_ALLOWED_MODULES = (
    "formation_agent.agent_node",
    "formation_bag.record_node",
    "formation_bag.replay_node",
    "formation_deploy.graph_watch",
)

#: (importer prefix, imported prefix): an importer under the first may not import anything under the second.
_PACKAGES = (  # bottom to top: a package may import only those before it
    "formation_core",
    "formation_msgs_py",
    "formation_ros",
    "formation_deploy",
    "formation_agent",
    "formation_bag",
    "formation_sim",
)
_SIM_TOP = ("formation_sim.node", "formation_sim.launch", "formation_sim.cli", "formation_sim.offline")
FORBIDDEN = (
    # the packages, bottom to top: nothing imports a package above its own
    *((low, high) for k, low in enumerate(_PACKAGES) for high in _PACKAGES[k + 1 :]),
    # formation_sim: cli -> launch | node | offline -> preflight -> core; views never drive a run
    *(("formation_sim.core", p) for p in (*_SIM_TOP, "formation_sim.views", "formation_sim.preflight")),
    *(("formation_sim.views", p) for p in (*_SIM_TOP, "formation_sim.preflight")),
    *(("formation_sim.preflight", p) for p in (*_SIM_TOP, "formation_sim.views")),
    *(("formation_sim.node", p) for p in ("formation_sim.launch", "formation_sim.cli", "formation_sim.offline")),
    *(("formation_sim.launch", p) for p in ("formation_sim.node", "formation_sim.cli", "formation_sim.offline")),
    *(("formation_sim.offline", p) for p in ("formation_sim.node", "formation_sim.launch", "formation_sim.cli")),
)

#: Modules that import a name computed at run time, and what it can be: these edges join the graph.
DYNAMIC_IMPORTS = {
    # msg_class: the message module (``<pkg>.msg``) of a recorded topic's type (docs/topics.md)
    "formation_bag.record_node": tuple(
        f"{pkg}.msg"
        for pkg in ("geometry_msgs", "std_msgs", "rosgraph_msgs", "diagnostic_msgs", "visualization_msgs", "tf2_msgs")
    ),
}
_IMPORT_CALLS = {"import_module", "__import__"}


@dataclass(frozen=True)
class Import:
    """One ``import`` statement of a module: what it names, where, and whether at module level."""

    module: str
    target: str
    line: int
    top_level: bool

    def __str__(self) -> str:
        where = "" if self.top_level else " (inside a function)"
        return f"{self.module} imports {self.target} at line {self.line}{where}"


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts[1:]  # src/<distribution>/<package>/...
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(SRC.glob("*/formation_*/**/*.py")):
        out[_module_name(path)] = path
    return out


def _package(module: str, path: Path) -> str:
    """The package a relative import of ``module`` starts from (the module itself for an ``__init__``)."""
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def _relative(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute name of ``from <dots><name> import …`` in ``module``."""
    base = _package(module, path)
    for _ in range(node.level - 1):
        base = base.rpartition(".")[0]
    return f"{base}.{node.module}" if node.module else base


def _called_name(call: ast.Call) -> str | None:
    """``import_module`` / ``__import__`` (bare or as an attribute), else None."""
    f = call.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    return name if name in _IMPORT_CALLS else None


DYNAMIC = "<computed at run time>"


def _imports(module: str, path: Path, source: str | None = None) -> list[Import]:
    """Every import in ``path`` (or in ``source``, as if it were that file's): ``from a.b import c`` names
    ``a.b.c`` and ``a.b`` (the graph keeps those that are modules), relative ones resolved,
    ``importlib.import_module("a.b")`` names ``a.b`` and one with a computed name :data:`DYNAMIC`;
    ``top_level`` is False inside a function (a lazy import)."""
    tree = ast.parse(path.read_text(encoding="utf-8") if source is None else source, str(path))
    out: list[Import] = []

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            names: list[str] = []
            if isinstance(child, ast.Import):
                names = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = _relative(module, path, child) if child.level else child.module or ""
                names = [f"{base}.{alias.name}" for alias in child.names] + [base]
            elif isinstance(child, ast.Call) and _called_name(child) and child.args:
                arg = child.args[0]
                literal = isinstance(arg, ast.Constant) and isinstance(arg.value, str)
                names = [arg.value if literal else DYNAMIC]  # type: ignore[union-attr]
            out.extend(Import(module, name, child.lineno, not in_function) for name in names)
            walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(tree, False)
    for target in DYNAMIC_IMPORTS.get(module, ()):
        out.append(Import(module, target, 0, False))
    return out


@functools.cache
def _graph() -> tuple[dict[str, list[Import]], dict[str, list[Import]]]:
    """(project edges per module, ROS imports per module). ``from a import b`` is an edge to ``a.b`` when
    ``a.b`` is a module, else to ``a``."""
    modules = _modules()
    edges: dict[str, list[Import]] = {m: [] for m in modules}
    ros: dict[str, list[Import]] = {m: [] for m in modules}
    for module, path in modules.items():
        seen: set[tuple[str, int]] = set()
        for imp in _imports(module, path):
            if imp.target == DYNAMIC:
                continue
            top_name = imp.target.split(".")[0]
            if top_name in _ROS_TOP or top_name.endswith("_msgs"):
                ros[module].append(imp)
                continue
            if not top_name.startswith("formation_"):
                continue
            target = imp.target
            while target not in modules and "." in target:
                target = target.rsplit(".", 1)[0]
            if target in modules and target != module and (target, imp.line) not in seen:
                seen.add((target, imp.line))
                edges[module].append(Import(module, target, imp.line, imp.top_level))
    return edges, ros


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def _ros_allowed(module: str) -> bool:
    return module in ROS_ALLOWED_MODULES or any(_under(module, p) for p in ROS_ALLOWED_PACKAGES)


def test_graph_is_read() -> None:
    """The parser finds the project's modules and their imports (a broken walk would pass every rule)."""
    edges, ros = _graph()
    assert "formation_core.spec" in edges and "formation_sim.core.loop" in edges
    assert any(e.target == "formation_core.schema" for e in edges["formation_core.spec"])
    assert any(e.target.split(".")[0] == "rclpy" for e in ros["formation_sim.node.sim_node"])
    lazy = [e for imports in edges.values() for e in imports if not e.top_level]
    assert lazy, "function-level imports are part of the graph"


def test_relative_and_importlib_imports_are_read() -> None:
    """The parser resolves ``from . import x``, ``from ..a import b`` and ``importlib.import_module("a.b")``
    (an import the graph did not see would pass every rule)."""
    source = (
        "from . import sibling\nfrom ..other import thing\nimport importlib\n"
        "def f():\n    importlib.import_module('formation_x.lazy')\n    return __import__(name)\n"
    )
    path = SRC / "formation_x" / "formation_x" / "pkg" / "mod.py"
    got = [(i.target, i.top_level) for i in _imports("formation_x.pkg.mod", path, source)]
    assert ("formation_x.pkg.sibling", True) in got and ("formation_x.other.thing", True) in got
    assert ("formation_x.lazy", False) in got and (DYNAMIC, False) in got


def test_every_computed_import_is_declared() -> None:
    """A module that imports a name computed at run time is in DYNAMIC_IMPORTS, which says what it loads
    (the graph cannot read it); and every declared one still does."""
    modules = _modules()
    dynamic = {m for m, path in modules.items() if any(i.target == DYNAMIC for i in _imports(m, path))}
    assert dynamic == set(DYNAMIC_IMPORTS), (
        f"computed imports not declared: {sorted(dynamic - set(DYNAMIC_IMPORTS))}; "
        f"declared but gone: {sorted(set(DYNAMIC_IMPORTS) - dynamic)}"
    )


def test_no_import_circles() -> None:
    """No module reaches itself through imports (a package's ``__init__`` re-exporting a submodule is an
    edge like any other)."""
    edges, _ = _graph()
    found: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    stack: list[str] = []

    def visit(module: str) -> None:
        state[module] = 1
        stack.append(module)
        for imp in edges[module]:
            if state.get(imp.target) == 1:
                found.append([*stack[stack.index(imp.target) :], imp.target])
            elif imp.target not in state:
                visit(imp.target)
        stack.pop()
        state[module] = 2

    for module in sorted(edges):
        if module not in state:
            visit(module)
    messages = []
    for circle in found:
        steps = [str(next(e for e in edges[a] if e.target == b)) for a, b in itertools.pairwise(circle)]
        message = "circle " + " -> ".join(circle) + ":\n    " + "\n    ".join(steps)
        if message not in messages:  # two imports of the same module in one function find a circle twice
            messages.append(message)
    assert not messages, "\n".join(messages)


def test_ros_is_imported_only_by_the_nodes() -> None:
    """rclpy and ROS message packages are imported only by formation_msgs_py.ros, formation_ros,
    formation_sim.node, the agent, recorder and replay nodes and the graph watch."""

    _, ros = _graph()
    bad = [str(imp) for module, imports in sorted(ros.items()) if not _ros_allowed(module) for imp in imports]
    assert not bad, "ROS imported outside the nodes:\n  " + "\n  ".join(bad)
    for module in ROS_ALLOWED_MODULES:
        assert ros[module], f"{module} no longer imports ROS: drop it from ROS_ALLOWED_MODULES"


def test_ros_free_modules_do_not_reach_ros_at_module_level() -> None:
    """Importing a module outside the nodes never imports ROS through a chain of module-level imports
    (an entry point may import its node inside a function: ``formation_agent.entry_point``)."""
    edges, ros = _graph()
    top_ros = {
        m: next(i for i in imports if i.top_level) for m, imports in ros.items() if any(i.top_level for i in imports)
    }
    bad = []
    for start in sorted(m for m in edges if not _ros_allowed(m)):
        chain = {start: [start]}
        todo = [start]
        while todo:
            module = todo.pop()
            for imp in edges[module]:
                if imp.top_level and imp.target not in chain:
                    chain[imp.target] = [*chain[module], imp.target]
                    todo.append(imp.target)
        bad += [" -> ".join(chain[m]) + f" ({top_ros[m]})" for m in sorted(set(chain) & set(top_ros))]
    assert not bad, "a module outside the nodes imports ROS through:\n  " + "\n  ".join(bad)


def test_imports_point_one_way() -> None:
    """No module imports a layer above its own: the FORBIDDEN pairs (the packages bottom to top, and
    formation_sim's folders: cli -> launch | node | offline -> preflight -> core)."""
    edges, _ = _graph()
    bad: dict[tuple[str, int, str], str] = {}  # one message per import statement and rule
    for module, imports in sorted(edges.items()):
        for imp in imports:
            for src, dst in FORBIDDEN:
                if _under(module, src) and _under(imp.target, dst):
                    bad.setdefault((module, imp.line, dst), f"{imp} (a {src} module may not import {dst})")
    assert not bad, "imports against the layering:\n  " + "\n  ".join(bad.values())


#: a module longer than this many lines says at the top of its docstring why it is one file
LONG_MODULE = 500
_WHY_ONE_FILE = f"Over {LONG_MODULE} lines:"


def test_a_long_module_says_why_it_is_one_file() -> None:
    """Every module under src/ over LONG_MODULE lines has a paragraph ``Over 500 lines: <why>`` in its
    docstring (a reason to keep it whole, or it is split); the rule is seen to apply (long modules exist)."""
    long, unexplained = [], []
    for path in _modules().values():
        text = path.read_text(encoding="utf-8")
        lines = text.count("\n")
        if lines > LONG_MODULE:
            long.append(path)
            doc = ast.get_docstring(ast.parse(text)) or ""
            if _WHY_ONE_FILE not in doc:
                unexplained.append(f"{path.relative_to(SRC)}: {lines} lines")
    assert long, "no module over the limit: the rule reads nothing"
    assert not unexplained, f"split these or say why at their top ({_WHY_ONE_FILE} …):\n  " + "\n  ".join(unexplained)
