"""The user documentation names only files that exist, and speaks of the project alone.

Checked: README.md, BENCHMARKS.md, docs/*.md and benchmarks/*.md. A path is a token that starts
with a top-level folder of the repository (``src/``, ``docs/``, ``config/``, ``benchmarks/``,
``ros2_ws/``, ``tests/``, ``docker/``, ``foxglove/``), anywhere in the text, or, inside backticks,
with a package folder (``formation_sim/core/loop.py`` is found under ``src/*/``). Markdown link
targets are relative to the page. Wildcards must match at least one file. A script named alone in
backticks (``floor_bench.py``, ``run.sh``) must be a file of the repository. A file the page's own
commands write (``--out FILE``, ``--results FILE``, ``> FILE``) need not exist.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted(
    [REPO / "README.md", REPO / "BENCHMARKS.md", *(REPO / "docs").glob("*.md"), *(REPO / "benchmarks").glob("*.md")]
)
TOP_FOLDERS = ("src", "docs", "config", "benchmarks", "ros2_ws", "tests", "docker", "foxglove")
PACKAGES = tuple(sorted(p.name for p in (REPO / "src").glob("*/*") if p.is_dir() and p.name == p.parent.name))

#: a repository path in running text: a top-level folder, then path characters
BARE_PATH = re.compile(rf"(?<![\w./~$-])(?:{'|'.join(TOP_FOLDERS)})/[\w./*-]*")
#: a path inside a backtick span may also start at a package folder
TICKED_PATH = re.compile(rf"^(?:{'|'.join(TOP_FOLDERS + PACKAGES)})/[\w./*-]*$")
#: a script named by its file name alone, inside backticks
SCRIPT = re.compile(r"^[\w.-]+\.(?:py|sh)$")
BACKTICKS = re.compile(r"`([^`\n]+)`")
#: a Markdown link or image target, without its #anchor
LINK = re.compile(r"\]\(([^)\s#]*)(?:#[^)]*)?\)")
#: a file a command on the page writes
WRITTEN = re.compile(r"(?:--out|--results|>)\s+([\w./-]+)")
#: what a page of the project must not say (development machines, people, diary entries, tickets)
DIARY = re.compile(
    r"/work/|/tmp/[a-z]+[0-9]+/|\b[Ss]essions?\b|\b[Ss]ittings?\b|\bthe lead\b|\bissues? [0-9]+|NOTES\.md"
    r"|shared machine"
)


def _repository_file_names() -> set[str]:
    """Names of the repository's files (not the virtual environment's, git's or caches')."""
    skip = {".git", ".venv", "__pycache__", "build", "install", "log"}
    names: set[str] = set()
    for _, folders, files in os.walk(REPO):
        folders[:] = [f for f in folders if f not in skip and not f.endswith(".egg-info")]
        names.update(files)
    return names


def _exists(token: str, page: Path, written: set[str]) -> bool:
    """Whether ``token`` names a file or folder of the repository (root, the page's folder, or under
    src/*/), or a file the page's commands write."""
    token = token.split("::")[0].rstrip(".,:;)")
    if not token or "..." in token or token in written:
        return True
    for base in (REPO, page.parent, *(p.parent for p in (REPO / "src").glob("*/*") if p.name in PACKAGES)):
        if any(c in token for c in "*?[") and any(base.glob(token)):
            return True
        if (base / token).exists():
            return True
    return False


def _lines(page: Path) -> list[tuple[int, str]]:
    """(line number, text) of every line of ``page``."""
    return list(enumerate(page.read_text(encoding="utf-8").splitlines(), start=1))


def test_every_path_named_in_the_docs_exists() -> None:
    """Every repository path in README.md, BENCHMARKS.md, docs/ and benchmarks/*.md exists."""
    missing = []
    names = _repository_file_names()
    for page in PAGES:
        written = set(WRITTEN.findall(page.read_text(encoding="utf-8")))
        for n, line in _lines(page):
            where = f"{page.relative_to(REPO)}:{n}"
            tokens = set(BARE_PATH.findall(line))
            for span in BACKTICKS.findall(line):
                tokens.update(t for t in span.split() if TICKED_PATH.match(t.rstrip(".,:;)")))
                missing += [f"{where}: {t}" for t in span.split() if SCRIPT.match(t) and t not in names]
            missing += [f"{where}: {t}" for t in sorted(tokens) if not _exists(t, page, written)]
    assert not missing, "paths that do not exist:\n" + "\n".join(missing)


def test_every_markdown_link_target_exists() -> None:
    """Every relative Markdown link (and image) in README.md, BENCHMARKS.md, docs/ and benchmarks/*.md exists."""
    missing = []
    for page in PAGES:
        for n, line in _lines(page):
            for target in LINK.findall(line):
                if target and "://" not in target and not target.startswith("mailto:"):
                    if not (page.parent / target).exists():
                        missing.append(f"{page.relative_to(REPO)}:{n}: {target}")
    assert not missing, "link targets that do not exist:\n" + "\n".join(missing)


def test_the_docs_speak_of_the_project_alone() -> None:
    """No development paths, people, sessions, issue numbers or reading-notes citations in the pages."""
    found = [
        f"{page.relative_to(REPO)}:{n}: {m.group(0)!r}"
        for page in PAGES
        for n, line in _lines(page)
        for m in DIARY.finditer(line)
    ]
    assert not found, "diary or development traces:\n" + "\n".join(found)
