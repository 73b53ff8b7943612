"""The README and docs/ as a reader meets them: every ```python block runs, every relative link
resolves, the README stays a front page, and every ``daemodel compare`` line parses.

The blocks of one file run in order in one fresh namespace, as a reader pastes them into one
session: a later block uses the names of an earlier one (``m``, ``c``).  They run in this process
(a fresh process per file would import torch and casadi again for each), in a temporary working
directory, with torch on one thread, and a block's traceback names its file and line.  ```bash and
```text blocks are not run.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README, *sorted(DOCS.rglob("*.md"))]
# A front page, not a manual: what it is, two commands, ten lines, one demo, links.
README_LIMIT_BYTES = 10 * 1024
# Files whose blocks train for longer than the fast suite allows; none today (the PINN guide's
# snippets use small networks and short spans).
SLOW_PAGES: set[str] = set()


def page_id(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def fenced_blocks(path: Path) -> list[tuple[str, int, str]]:
    """Each fenced block of a Markdown file as (language, line of its first code line, source)."""
    blocks, language, start, body = [], None, 0, []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if language is None and line.startswith("```"):
            language, start, body = line[3:].strip(), number + 1, []
        elif language is not None and line.startswith("```"):
            blocks.append((language, start, "\n".join(body) + "\n"))
            language = None
        elif language is not None:
            body.append(line)
    if language is not None:
        raise AssertionError(f"{page_id(path)}: the block opened at line {start - 1} is never closed")
    return blocks


def prose(path: Path) -> str:
    """The file without its fenced blocks and inline code (links inside code are not links)."""
    lines, inside = [], False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            inside = not inside
        elif not inside:
            lines.append(re.sub(r"`[^`]*`", "", line))
    return "\n".join(lines)


def anchors(path: Path) -> set[str]:
    """GitHub's anchors for the headings of a Markdown file: lower case, punctuation dropped,
    spaces as hyphens."""
    found, inside = set(), False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            inside = not inside
        elif not inside and (heading := re.match(r"#{1,6} (.*)", line)):
            found.add(re.sub(r"[^\w\- ]", "", heading.group(1).strip().lower()).replace(" ", "-"))
    return found


def test_the_pages_have_blocks_to_run():
    """Guards the parametrisation below against finding nothing (a renamed folder, a changed fence)."""
    assert README.exists() and (DOCS / "README.md").exists()
    assert len(PAGES) >= 10
    assert [language for language, _, _ in fenced_blocks(README)].count("python") >= 2
    assert sum(lang == "python" for page in PAGES for lang, _, _ in fenced_blocks(page)) >= 12


def test_every_fence_names_its_language():
    """An unlabelled block would be neither run nor knowingly skipped."""
    unlabelled = [f"{page_id(page)}:{line - 1}" for page in PAGES for lang, line, _ in fenced_blocks(page) if not lang]
    assert not unlabelled, f"label these blocks python, bash or text: {unlabelled}"


def test_readme_is_a_front_page():
    size = README.stat().st_size
    assert size <= README_LIMIT_BYTES, f"README.md is {size} bytes; move detail into docs/ (limit {README_LIMIT_BYTES})"


def python_blocks(page: Path) -> list[tuple[int, str]]:
    return [(line, source) for language, line, source in fenced_blocks(page) if language == "python"]


@pytest.mark.parametrize(
    "page",
    [
        pytest.param(page, id=page_id(page), marks=[pytest.mark.slow] * (page_id(page) in SLOW_PAGES))
        for page in PAGES
        if python_blocks(page)
    ],
)
def test_python_blocks_run(page, tmp_path, monkeypatch, request):
    blocks = python_blocks(page)
    if any(re.search(r'^[^#\n]*(?:engine|executor)="ray"', source, re.M) for _, source in blocks):
        request.getfixturevalue("ray_cluster")  # the tests' local cluster of 2 CPUs (skipped without Ray)
    import matplotlib
    import torch

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    namespace = {"__name__": "__main__"}
    try:
        for line, source in blocks:
            # Our own documentation, run as a reader would paste it: exec is the point of the test.
            # Leading newlines put a traceback's line numbers on the Markdown file's lines.
            exec(compile("\n" * (line - 1) + source, str(page), "exec"), namespace)
    finally:
        torch.set_num_threads(threads)
        plt.close("all")


def relative_links(page: Path) -> list[str]:
    targets = re.findall(r"\]\(([^)\s]+)\)", prose(page))
    return [t for t in targets if not re.match(r"[a-z]+:", t)]  # http:, https:, mailto:


@pytest.mark.parametrize("page", PAGES, ids=page_id)
def test_relative_links_resolve(page):
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{target} (no heading '{anchor}' in {page_id(file)})")
    assert not broken, f"{page_id(page)}: broken links {broken}"


def test_every_docs_page_is_in_the_table_of_contents():
    listed = {(DOCS / target.partition("#")[0]).resolve() for target in relative_links(DOCS / "README.md")}
    missing = [page_id(page) for page in PAGES[1:] if page != DOCS / "README.md" and page not in listed]
    assert not missing, f"docs/README.md does not list {missing}"


def compare_lines() -> list[tuple[str, str]]:
    """(page, command) for every ``daemodel compare`` command in a ```bash block."""
    found = []
    for page in PAGES:
        for language, _, source in fenced_blocks(page):
            if language == "bash":
                for line in source.splitlines():
                    for command in line.split("&&"):
                        if command.strip().startswith("daemodel compare"):
                            found.append((page_id(page), command.strip()))
    return found


def test_the_readme_demo_is_the_one_ci_runs():
    """.ci/run runs "README command 1"; the two must not drift apart."""
    demo = [command for page, command in compare_lines() if page == "README.md"]
    assert demo == ["daemodel compare hessenberg pendulum"]
    assert "daemodel compare hessenberg pendulum --no-progress" in (ROOT / ".ci" / "run").read_text()


@pytest.mark.parametrize(("page", "command"), compare_lines(), ids=lambda value: value)
def test_compare_commands_parse(page, command):
    from daemodel.backends import methods

    from daemodel.comparing.cli import _parser

    args = _parser().parse_args(shlex.split(command, comments=True)[1:])
    assert args.command == "compare" and args.targets
    if args.methods is not None:
        unknown = set(args.methods.split(",")) - set(methods())
        assert not unknown, f"{page}: {command!r} names unknown methods {unknown}"
