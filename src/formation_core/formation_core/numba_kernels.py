"""The one switch between the compiled (numba) and the interpreted form of the numerical kernels.

The controller, the SO(3) maps, the funnels, the plant and the closed-loop stepping are written
once, as plain Python on floats, tuples and small numpy arrays. A :func:`kernel` is an entry point
called from Python: compiled per argument types (``numba.njit``) and cached on disk, so that a
second process loads the machine code instead of compiling it. A :func:`formula` is every other
function: compiled into the kernels that call it, typed by its arguments' types (never by their
literal values: a formula called with ``0`` and with ``i`` is compiled once), with no Python or C
entry of its own. ``NUMBA_DISABLE_JIT=1`` runs every kernel and formula as the Python it is
written in; each compiled kernel also keeps that Python as ``.py_func``.

A first run compiles every (function, argument types) it meets, each through numba's typing and
lowering and LLVM, so the code keeps that set small: formulas take 3-vectors as tuples and 3×3
matrices as row tuples (:func:`formation_core.so3.vec3` and :func:`formation_core.so3.matrix_rows`
read them from arrays), every call site of a kernel passes the same types (C-contiguous arrays),
and a kernel's own body calls formulas that no other formula calls (numba compiles a formula once
per kind of caller, kernel or formula: the SO(3) products and funnels are called from formulas only).

``error_model="numpy"``: a division by zero gives inf/NaN as in numpy instead of raising; the
callers check finiteness where the paper's law can leave its domain.

``_nrt=False``: the kernels run without numba's reference-counting runtime. They cannot allocate
(an ``np.empty``, a ``.copy()`` or a slice assignment does not compile: callers preallocate and
kernels write element by element), and no array they pass on costs an atomic increment and
decrement per call: with the runtime, those were most of a control step's time.

The on-disk cache of a kernel is keyed on every source compiled into it. numba alone keys it on
the kernel's own file, but a kernel's machine code also holds the formulas, kernels and constants
of the modules it imports (the run core compiles the controller, the funnels, the plant and the
SO(3) maps from five files): an edit of a callee would leave a stale kernel in the cache. Here a
kernel's key is :func:`sources_stamp`, a hash of its module's file and of every ``formation_*``
module that file imports, transitively (read from the ``import`` lines, without importing them);
it is the index's freshness stamp and part of the index's file name, so that any edit or upgrade
of one of those files compiles the kernel again, and trees that differ keep their own entries.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable)

#: True when ``NUMBA_DISABLE_JIT`` is set (not "0"): every kernel is its own Python source, and
#: numba is not even imported (an agent process saves its start time and memory).
INTERPRETED = os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0")


#: the code forms a kernel runs in: machine code from numba, or its own Python source
FORM_COMPILED, FORM_INTERPRETED = "compiled", "interpreted"
#: this process's form
CODE_FORM = FORM_INTERPRETED if INTERPRETED else FORM_COMPILED

#: environment variables that change the machine code numba emits or the SIMD paths numpy takes
_NUMERIC_ENVIRONMENT = (
    "NPY_DISABLE_CPU_FEATURES",
    "NPY_ENABLE_CPU_FEATURES",
    "NUMBA_CPU_NAME",
    "NUMBA_CPU_FEATURES",
    "NUMBA_OPT",
    "NUMBA_FASTMATH",
)


def in_code_form(fn: F, form: str) -> F | None:
    """Kernel ``fn`` as code of ``form`` (:data:`FORM_COMPILED` or :data:`FORM_INTERPRETED`): the
    kernel itself in this process's form, its Python source for the interpreted form of a compiled
    process; None where this process cannot run that form (compiled code in an interpreted process)."""
    if form == CODE_FORM:
        return fn
    if form == FORM_INTERPRETED:
        return fn.py_func  # type: ignore[attr-defined]  # a numba dispatcher keeps its Python
    return None


def numeric_platform() -> str:
    """A fingerprint of what decides the bits a kernel computes in this process besides its inputs:
    the host and its CPU, the interpreter and its environment (the installed numpy and numba), libc,
    and the variables that steer numba's code generation and numpy's SIMD dispatch. Two processes
    with equal fingerprints and the same :data:`CODE_FORM` compute the same bits from the same
    inputs; with different ones they may differ in the last places."""
    import importlib.metadata
    import json
    import platform

    cpu = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = "".join(line for line in f if line.startswith(("model name", "flags")))
    except OSError:
        cpu = platform.processor()
    versions = {}
    for package in ("numpy", "numba", "llvmlite"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = ""
    facts = {
        "host": platform.node(),
        "machine": platform.machine(),
        "cpu": hashlib.sha256(cpu.encode()).hexdigest(),
        "python": sys.version,
        "prefix": sys.prefix,
        "libc": platform.libc_ver(),
        "versions": versions,
        "environment": {name: os.environ.get(name, "") for name in _NUMERIC_ENVIRONMENT},
    }
    return hashlib.sha256(json.dumps(facts, sort_keys=True).encode()).hexdigest()[:16]


#: formulas declared before numba was imported, registered at the first :func:`kernel`
_PENDING: list[Callable] = []


def formula(fn: F) -> F:
    """A function compiled into every kernel that calls it (an SO(3) product, a funnel, a step of
    the controller): plain Python when called from Python (where numpy arrays work elementwise).

    Declaring it does not import numba (``formation_core.spec`` uses funnels and SO(3) maps
    and is imported by every command); :func:`kernel` registers it before any kernel compiles.
    """
    if not INTERPRETED:
        _PENDING.append(fn)
        if _numba is not None:
            _register_pending()
    return fn


def kernel(fn: F) -> F:
    """Compile ``fn`` in nopython mode, cached next to its source (or in ``NUMBA_CACHE_DIR``).

    No C entry (``no_cfunc_wrapper``): kernels are called from Python or from other kernels, never
    as C function pointers, and the wrapper is LLVM work at every compilation.
    """
    if INTERPRETED:
        return fn
    numba = _import_numba()
    _register_pending()
    dispatcher = numba.njit(error_model="numpy", _nrt=False, no_cfunc_wrapper=True)(fn)
    dispatcher._cache = _sources_cache()(fn)  # what ``cache=True`` sets, keyed on the sources (module doc)
    return dispatcher


def kernel_cached(dispatcher: Any) -> bool:
    """Whether numba's cache holds an index of ``dispatcher``'s kernel for the sources as they are now
    (numba's private ``_cache._cache_file._index_path``: tests/formation_core/test_numba_kernels.py checks
    it); False interpreted."""
    if INTERPRETED:
        return False
    return Path(dispatcher._cache._cache_file._index_path).exists()


_numba = None

#: Modules numba imports that no kernel needs, together a few tenths of a second of every compiled
#: process's start: ``coverage`` (numba's coverage support, when coverage is installed and not
#: running), scipy (numba checks its version, and ``numba.np.arraymath`` imports scipy.linalg to
#: check for a BLAS that only its np.convolve/np.correlate would use; np.dot and np.linalg import it
#: when they compile) and cffi (numba's typing of cffi functions).
_NOT_NEEDED = ("coverage", "scipy", "cffi")


def _import_numba() -> ModuleType:
    """numba, and the modules of it that import :data:`_NOT_NEEDED` (else imported by its first cache
    load or compilation), imported while those are hidden; later importers find them as usual."""
    global _numba
    if _numba is None:
        hidden = [name for name in _NOT_NEEDED if name not in sys.modules]
        # None in sys.modules: ``import`` fails at once (the import system's documented blocker, which
        # typeshed's dict[str, ModuleType] does not express)
        sys.modules.update(dict.fromkeys(hidden))  # type: ignore[arg-type]
        try:
            import numba
            import numba.core.typing.cffi_utils
            import numba.np.arraymath
        finally:
            for name in hidden:
                sys.modules.pop(name, None)
        _numba = numba
    return _numba


def _register_pending() -> None:
    from numba.extending import register_jitable

    while _PENDING:
        register_jitable(error_model="numpy", _nrt=False, no_cfunc_wrapper=True)(_PENDING.pop())


# --- the cache key: every source compiled into a kernel ------------------------------------------

#: ``from formation_x[.y] import a, b`` (also parenthesised over lines) and ``import formation_x[.y]``
_IMPORT = re.compile(
    rb"^[ \t]*(?:from[ \t]+(formation_[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)|import[ \t]+(formation_[^\n]*))",
    re.MULTILINE,
)
#: characters of :func:`sources_stamp` in an index's file name
STAMP_IN_NAME = 16
#: file -> ((mtime_ns, size), sha256 of its bytes, the formation_* names its import lines name)
_SCANNED: dict[Path, tuple[tuple[int, int], bytes, tuple[str, ...]]] = {}
#: top-level package name -> its directories (None: not found)
_PACKAGE_DIRS: dict[str, list[Path] | None] = {}
#: module name -> its source file (None: not a module)
_MODULE_FILES: dict[str, Path | None] = {}


def _scan(path: Path) -> tuple[bytes, tuple[str, ...]]:
    """(sha256 of ``path``'s bytes, the names its ``formation_*`` import lines name), memoised per mtime and size."""
    st = path.stat()
    key = (st.st_mtime_ns, st.st_size)
    known = _SCANNED.get(path)
    if known is not None and known[0] == key:
        return known[1], known[2]
    data = path.read_bytes()
    names: list[str] = []
    for m in _IMPORT.finditer(data):
        if m.group(1):  # from M import a, b: M, and M.a, M.b where those are modules
            module = m.group(1).decode()
            listed = m.group(2).split(b"#", 1)[0] if not m.group(2).startswith(b"(") else m.group(2)
            listed = re.sub(rb"#[^\n]*", b"", listed)
            names.append(module)
            names.extend(f"{module}.{n.decode()}" for n in re.findall(rb"\w+", listed) if n != b"as")
        else:  # import M[.N] [as x], ...
            names.extend(n.decode() for n in re.findall(rb"formation_[\w.]*", m.group(3).split(b"#", 1)[0]))
    scanned = (key, hashlib.sha256(data).digest(), tuple(names))
    _SCANNED[path] = scanned
    return scanned[1], scanned[2]


def _module_file(name: str) -> Path | None:
    """The source file of module ``name`` (a package's ``__init__.py``), found without importing it;
    None if it is not a module (an imported function or constant)."""
    if name not in _MODULE_FILES:
        _MODULE_FILES[name] = _find_module_file(name)
    return _MODULE_FILES[name]


def _find_module_file(name: str) -> Path | None:
    top, *rest = name.split(".")
    if top not in _PACKAGE_DIRS:
        spec = importlib.util.find_spec(top) if top not in sys.modules else sys.modules[top].__spec__
        locations = None if spec is None else spec.submodule_search_locations
        _PACKAGE_DIRS[top] = None if locations is None else [Path(d) for d in locations]
    for base in _PACKAGE_DIRS[top] or ():
        path = base.joinpath(*rest)
        for candidate in (path.with_suffix(".py"), path / "__init__.py") if rest else (path / "__init__.py",):
            if candidate.is_file():
                return candidate.resolve()
    return None


def sources_stamp(path: str | os.PathLike[str]) -> str:
    """SHA-256 (hex) of the source file ``path`` and of every ``formation_*`` module it imports,
    transitively (the files' contents, not their places): the cache key of the kernels in ``path``."""
    root = Path(path).resolve()
    seen = {root}
    todo = [root]
    digests = []
    while todo:
        digest, names = _scan(todo.pop())
        digests.append(digest)
        for name in names:
            found = _module_file(name)
            if found is not None and found not in seen:
                seen.add(found)
                todo.append(found)
    return hashlib.sha256(b"".join(sorted(digests))).hexdigest()


def cache_index_glob(py_file: str | os.PathLike[str], qualname: str) -> list[Path]:
    """The places numba's cache may hold the index of kernel ``qualname`` of ``py_file`` for the
    sources as they are now (glob patterns, in numba's order of preference: ``NUMBA_CACHE_DIR``,
    the ``__pycache__`` beside the file, the user-wide cache); read without importing numba."""
    py_file = Path(py_file).resolve()
    stamp = sources_stamp(py_file)[:STAMP_IN_NAME]
    name = f"{py_file.stem}.{qualname}-*-{stamp}.py{sys.version_info[0]}{sys.version_info[1]}{sys.abiflags}.nbi"
    # numba's cache subfolder of a source folder: its name and the SHA-1 of its path
    # (numba.core.caching._CacheLocator.get_suitable_cache_subpath)
    subpath = f"{py_file.parent.name}_{hashlib.sha1(str(py_file.parent).encode()).hexdigest()}"
    dirs = [py_file.parent / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        dirs.insert(0, Path(os.environ["NUMBA_CACHE_DIR"]) / subpath)
    user_cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba"
    dirs.append(user_cache / subpath)
    return [d / name for d in dirs]


_SOURCES_CACHE: type | None = None


def _sources_cache() -> type:
    """numba's per-function disk cache with the locators' stamp and file name keyed on
    :func:`sources_stamp` (private numba API: tests/formation_core/test_numba_kernels.py checks it)."""
    global _SOURCES_CACHE
    if _SOURCES_CACHE is None:
        from numba.core import caching

        def keyed(locator: Any) -> type[object]:  # Any: a base class chosen at run time
            class SourcesKeyed(locator):
                def get_source_stamp(self) -> str:
                    if not hasattr(self, "_sources_stamp"):  # numba asks twice: for the index and its name
                        self._sources_stamp = sources_stamp(self._py_file)
                    return self._sources_stamp

                def get_disambiguator(self) -> str:
                    return f"{super().get_disambiguator()}-{self.get_source_stamp()[:STAMP_IN_NAME]}"

            SourcesKeyed.__name__ = SourcesKeyed.__qualname__ = f"SourcesKeyed{locator.__name__}"
            return SourcesKeyed

        class SourcesCacheImpl(caching.CompileResultCacheImpl):
            # the locators of a source file on disk (not a notebook cell or a zip archive)
            _locator_classes = [  # noqa: RUF012 (numba reads this class attribute)
                keyed(c)
                for c in caching.CompileResultCacheImpl._locator_classes
                if issubclass(c, caching._SourceFileBackedLocatorMixin) and c is not caching.ZipCacheLocator
            ]

        class SourcesFunctionCache(caching.FunctionCache):
            _impl_class = SourcesCacheImpl

        _SOURCES_CACHE = SourcesFunctionCache
    return _SOURCES_CACHE
