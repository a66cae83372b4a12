"""Every relative link of the repository's Markdown files points at a file or folder that exists (stale paths after
a module moves fail here). External URLs, mail addresses, in-page anchors and data URIs are not checked; the
generated benchmark results (``benchmarks/results/``) are left out. An anchor after a path (``README.md#set-up``)
is dropped: the file must exist, the heading is not checked."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIPPED_DIRS = ("benchmarks/results",)
# [text](target) and ![alt](target), the target up to whitespace or ")"; reference definitions "[id]: target"
INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+[\"'(][^)]*)?\)")
REFERENCE = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)")
FENCE = re.compile(r"^\s*(```|~~~)")
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")
EXTERNAL = re.compile(r"^(?:[a-zA-Z][a-zA-Z0-9+.-]*:|//|#)")  # http:, https:, mailto:, data:, //host, #anchor


def markdown_files(root: Path = ROOT) -> list[Path]:
    """The repository's Markdown files: git's tracked and untracked-but-not-ignored ones (a fresh clone's), or,
    without git, every one outside hidden folders; never those under ``SKIPPED_DIRS``."""
    try:
        out = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "--", "*.md"], cwd=root, check=True,
                             capture_output=True, text=True, timeout=30).stdout.splitlines()
        paths = [root / p for p in out]
    except (OSError, subprocess.SubprocessError):
        paths = []
        for d, dirs, files in os.walk(root):
            dirs[:] = [x for x in dirs if not x.startswith(".") and x != "__pycache__" and not x.endswith(".egg-info")]
            paths += [Path(d) / f for f in files if f.endswith(".md")]
    return sorted(p for p in paths if p.is_file()
                  and not any(p.relative_to(root).as_posix().startswith(s + "/") for s in SKIPPED_DIRS))


def relative_links(text: str) -> list[tuple[int, str]]:
    """``(line number, target)`` of every relative link outside code blocks and code spans."""
    links, fenced = [], False
    for n, line in enumerate(text.splitlines(), start=1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        line = CODE_SPAN.sub("", line)
        targets = [m.group(1) for m in INLINE.finditer(line)]
        if (m := REFERENCE.match(line)) is not None:
            targets.append(m.group(1))
        links += [(n, t) for t in targets if not EXTERNAL.match(t)]
    return links


def broken_links(path: Path, root: Path = ROOT) -> list[str]:
    """``file:line: target`` of each relative link of ``path`` that names nothing on disk (a leading ``/`` is the
    repository root, as GitHub reads it)."""
    bad = []
    for n, target in relative_links(path.read_text(encoding="utf-8")):
        rel = target.split("#", 1)[0].split("?", 1)[0]
        if not rel:
            continue
        dest = root / rel.lstrip("/") if rel.startswith("/") else path.parent / rel
        if not dest.exists():
            bad.append(f"{path.relative_to(root).as_posix()}:{n}: {target}")
    return bad


def test_every_relative_markdown_link_resolves():
    files = markdown_files()
    assert any(p.name == "README.md" and p.parent == ROOT for p in files)  # the walk found the repository's docs
    bad = [b for p in files for b in broken_links(p)]
    assert not bad, "stale links (fix the path or the file's name):\n" + "\n".join(bad)


@pytest.mark.parametrize(("line", "broken"), [
    ("[the store](schemas/README.md)", False),
    ("[its heading](schemas/README.md#step-protocol-and-resuming)", False),
    ("![a figure](docs/viewer.png)", False),
    ("[a folder](models/zoo/)", False),
    ("[from the root](/tasks/readers.py)", False),
    ("[the web](https://example.org/missing.md), [mail](mailto:a@b.c), [here](#anchor)", False),
    ("`[in code](nothing/here.md)`", False),
    ("[old home](models/runtime/hub.py)", True),
    ("[old test](tests/models/runtime/test_hub.py#L3)", True),
    ('[titled](no/such/file.md "a title")', True),
    ("[ref]: models/refiner/difix.py", True),
])
def test_the_check_finds_broken_links(tmp_path, line, broken):
    for rel in ("schemas/README.md", "docs/viewer.png", "models/zoo/x.py", "tasks/readers.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    doc = tmp_path / "README.md"
    doc.write_text(f"# doc\n\n```\n[fenced](nothing/here.md)\n```\n{line}\n")
    bad = broken_links(doc, tmp_path)
    assert bool(bad) == broken, bad
    if broken:
        assert bad[0].startswith("README.md:6: ")
