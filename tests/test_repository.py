"""The repository stands on its own and describes what is, checked over every tracked text file.

- No file cites a path outside the repository: a ``../`` path that leaves the repository root
  (resolved from the file's folder), the shared folder beside the checkout, or an absolute path
  on a developer's machine (``/work/``, ``/home/``, ``/Users/``, ``/root/``). Scratch output
  folders such as ``/tmp/...`` in example commands are fine.
- No file tells history by number ("issue N", "session N"): say what the code does and why.
- Every ``docs/model.md §N`` citation names a section heading that exists in docs/model.md.
- Every relative link in a Markdown file resolves to a file of the repository.

Each check is a function of text, so the tests below also show that each one can fail.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "docs" / "model.md"

#: The word, an optional plural "s", an optional "#" and a number (case-insensitive).
HISTORY = re.compile(r"\b(issue|session)s? #?\d+", re.IGNORECASE)
#: Absolute paths on a developer's machine.
ABSOLUTE = re.compile(r"(?<![\w.~/-])/(work|home|Users|root)/[\w.-][\w./-]*")
#: A relative path that climbs one or more folders (not preceded by a path character).
CLIMB = re.compile(r"(?<![\w.~/-])((?:\.\./)+)([\w.-]*)")
#: The shared folder beside the checkout, wherever it is cited from.
SHARED = re.compile(r"(?<![\w-])" + re.escape("..") + r"/shared\b")
#: A citation of the model document and the section numbers that follow it.
CITATION = re.compile(r"docs/model\.md((?:\s*(?:,|and|or|to|-)?\s*§\d+)+)")
#: Markdown links and images: ``[text](target)``.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
#: Skipped: build outputs and caches that may lie in a working tree.
_SKIP_PARTS = {".git", ".venv", "__pycache__", ".pytest_cache", "build", "dist", ".ipynb_checkpoints"}


def tracked_files() -> list[Path]:
    """The repository's tracked files (``git ls-files``); without git, every file under the
    root outside caches and build outputs."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
        names = [n for n in out.stdout.decode().split("\0") if n]
        if names:
            return [ROOT / n for n in names if (ROOT / n).is_file()]
    except (OSError, subprocess.CalledProcessError):
        pass
    return [p for p in ROOT.rglob("*") if p.is_file()
            and not _SKIP_PARTS.intersection(p.relative_to(ROOT).parts)
            and not p.name.endswith(".egg-info")]


def read_text(path: Path) -> str | None:
    """The file as UTF-8 text, or None for a binary file (a NUL byte, or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def text_files() -> dict[str, str]:
    """Repository-relative path -> text of every tracked text file."""
    out = {}
    for p in tracked_files():
        text = read_text(p)
        if text is not None:
            out[p.relative_to(ROOT).as_posix()] = text
    return out


def _lines(text: str, pattern: re.Pattern):
    for i, line in enumerate(text.splitlines(), 1):
        for m in pattern.finditer(line):
            yield i, m


def outside_paths(rel: str, text: str) -> list[str]:
    """Places where the file ``rel`` (repository-relative) cites a path outside the repository."""
    found = []
    depth = len(Path(rel).parent.parts)
    for i, m in _lines(text, SHARED):
        found.append(f"{rel}:{i}: cites {m.group(0)!r}")
    for i, m in _lines(text, ABSOLUTE):
        found.append(f"{rel}:{i}: absolute path {m.group(0)!r}")
    for i, m in _lines(text, CLIMB):
        ups = m.group(1).count("../")
        if ups > depth:
            found.append(f"{rel}:{i}: {m.group(0)!r} leaves the repository")
    return sorted(set(found))


def history_mentions(rel: str, text: str) -> list[str]:
    """Places where ``rel`` tells history by number ("issue N", "session N")."""
    return [f"{rel}:{i}: {m.group(0)!r}" for i, m in _lines(text, HISTORY)]


def model_sections(model_text: str) -> set[int]:
    """Section numbers of docs/model.md's headings (``## 3. The pair integral`` -> 3)."""
    return {int(m.group(1)) for m in re.finditer(r"^#{2,3} (\d+)\.", model_text, re.MULTILINE)}


def bad_citations(rel: str, text: str, sections: set[int]) -> list[str]:
    """``docs/model.md §N`` citations in ``rel`` whose section does not exist (in docs/model.md
    itself, every bare ``§N`` too)."""
    found = []
    for m in CITATION.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        for n in re.findall(r"§(\d+)", m.group(1)):
            if int(n) not in sections:
                found.append(f"{rel}:{line}: docs/model.md §{n} does not exist")
    if rel == "docs/model.md":
        for i, m in _lines(text, re.compile(r"§(\d+)")):
            if int(m.group(1)) not in sections:
                found.append(f"{rel}:{i}: §{m.group(1)} does not exist")
    return sorted(set(found))


def broken_links(rel: str, text: str, exists=None) -> list[str]:
    """Relative Markdown links in ``rel`` that do not resolve to a file of the repository.
    ``exists(path relative to the root) -> bool`` (default: the file system)."""
    if exists is None:
        exists = lambda p: (ROOT / p).exists()  # noqa: E731
    found = []
    base = Path(rel).parent
    for i, m in _lines(text, LINK):
        target = m.group(1).strip("<>")
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("#"):
            continue  # a URL (https:, mailto:) or an anchor in the same file
        path = target.split("#", 1)[0].split("?", 1)[0]
        parts = []
        for part in (base / path).parts:
            if part == "..":
                if not parts:
                    parts = None
                    break
                parts.pop()
            elif part != ".":
                parts.append(part)
        if parts is None:
            found.append(f"{rel}:{i}: link {target!r} leaves the repository")
        elif not parts or not exists("/".join(parts)):
            found.append(f"{rel}:{i}: link {target!r} does not resolve")
    return found


# --- the repository -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def files() -> dict[str, str]:
    return text_files()


def test_the_scan_sees_the_repository(files):
    for rel in ("README.md", "docs/model.md", "jscratch/ndf.py", "tests/test_repository.py"):
        assert rel in files
    assert not any(rel.endswith(".png") for rel in files)  # binary files are skipped


def test_no_path_outside_the_repository(files):
    found = [f for rel, text in files.items() for f in outside_paths(rel, text)]
    assert not found, "\n".join(found)


def test_no_history_by_number(files):
    found = [f for rel, text in files.items() for f in history_mentions(rel, text)]
    assert not found, "\n".join(found)


def test_every_model_citation_names_an_existing_section(files):
    sections = model_sections(files["docs/model.md"])
    assert set(range(1, 10)) <= sections  # the numbered sections §1-§9 keep their numbers
    found = [f for rel, text in files.items() for f in bad_citations(rel, text, sections)]
    assert not found, "\n".join(found)


def test_every_relative_markdown_link_resolves(files):
    found = [f for rel, text in files.items() if rel.endswith(".md")
             for f in broken_links(rel, text)]
    assert not found, "\n".join(found)


# --- the checks can fail ------------------------------------------------------------------------

@pytest.mark.parametrize("line", [
    "The model is fixed by `" + ".." + "/shared/SPEC.md`.",
    "see " + "/wo" + "rk/main/jscratch/ndf.py",
    "open('" + "../" * 3 + "notes.txt')",
])
def test_outside_paths_are_found(line):
    assert outside_paths("jscratch/x.py", f"ok\n{line}\n")
    assert not outside_paths("jscratch/x.py", "python -m jscratch.design --out /tmp/run\n")
    assert not outside_paths("docs/x.md", "[the readme](../README.md)\n")


@pytest.mark.parametrize("line", ["measured in " + "issue" + " 17", "since " + "Session" + " 9",
                                  "(" + "issues" + " #2 and 3)"])
def test_history_mentions_are_found(line):
    assert history_mentions("x.py", f"fine\n{line}\n") == [
        f"x.py:2: {HISTORY.search(line).group(0)!r}"]
    assert not history_mentions("x.py", "a journal records each carving session\n")


def test_bad_citations_are_found():
    sections = model_sections("# Model\n\n## 1. Frames\n\n## 3. The pair integral\n")
    assert sections == {1, 3}
    cite = "docs/model" + ".md"
    assert not bad_citations("x.py", f"see {cite} §1 and {cite} §1-§3", sections)
    assert bad_citations("x.py", f"see {cite} §2", sections) == [
        f"x.py:1: {cite} §2 does not exist"]
    assert bad_citations("x.py", f"({cite}\n§1, §2 and §3)", sections)


def test_broken_links_are_found():
    exists = {"docs/model.md", "README.md"}.__contains__
    up = "../" * 2 + "outside.md"
    text = ("[m](model.md) [r](../README.md#fresh-machine) [w](https://example.org) [a](#top)\n"
            f"[gone](missing.md)\n[up]({up})\n")
    assert broken_links("docs/x.md", text, exists) == [
        "docs/x.md:2: link 'missing.md' does not resolve",
        f"docs/x.md:3: link {up!r} leaves the repository"]
