"""The README and docs/ pages: short README, links that resolve, every page reachable,
commands that parse.

Pure text checks (no simulation): they keep the documentation navigable as files move.
"""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from glaciar.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README] + sorted(DOCS.glob("*.md"))

#: the README a newcomer reads in five minutes (issue 22)
README_MAX_LINES = 200

# [text](target) and <a href="target">; images ![..](..) are links too.
_LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|href=\"([^\"]+)\"")
_FENCE = re.compile(r"^```.*?^```", re.S | re.M)
_HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _prose(path: Path) -> str:
    """The page without its fenced code blocks (links inside code are not links)."""
    return _FENCE.sub("", _text(path))


def _links(path: Path) -> list[str]:
    return [a or b for a, b in _LINK.findall(_prose(path))]


def _is_relative(target: str) -> bool:
    return not re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I)   # http:, https:, mailto:, ...


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces -> '-'."""
    text = re.sub(r"[`*_]", "", heading).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    return {_slug(h) for h in _HEADING.findall(_prose(path))}


def test_readme_is_short():
    n = len(_text(README).splitlines())
    assert n <= README_MAX_LINES, f"README.md: {n} lines, at most {README_MAX_LINES}"


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_relative_links_resolve(page):
    broken = []
    for target in _links(page):
        if not _is_relative(target):
            continue
        file_part, _, anchor = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.exists():
            broken.append(f"{target} (no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest})")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target} (no heading #{anchor} in {dest.name})")
    assert not broken, f"{page.relative_to(ROOT)}: broken links: {broken}"


def test_every_docs_page_is_linked_from_readme():
    linked = {(README.parent / t.partition("#")[0]).resolve()
              for t in _links(README) if _is_relative(t) and t.partition("#")[0]}
    pages = {p.resolve() for p in DOCS.iterdir() if p.is_file()}
    missing = sorted(p.name for p in pages - linked)
    assert not missing, f"docs/ pages not linked from README.md: {missing}"


# Repository files the pages name in prose or code (`benchmarks/x.py`, `tests/test_x.py`, ...).
_REPO_PATH = re.compile(r"(?<![\w/.-])((?:benchmarks|tests|configs|notebooks|scripts|docs|\.ci)/"
                        r"[\w./-]*\w)")


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_named_repository_files_exist(page):
    missing = sorted({m for m in _REPO_PATH.findall(_text(page))
                      if "*" not in m and not (ROOT / m).exists()})
    assert not missing, f"{page.relative_to(ROOT)} names files that do not exist: {missing}"


def test_readme_test_command_is_what_ci_runs():
    # .ci/run ends with the README's test command, and scripts/test.sh is what it runs.
    ci = [ln.strip() for ln in _text(ROOT / ".ci" / "run").splitlines()
          if ln.strip() and not ln.lstrip().startswith("#")]
    assert ci[-1] == "bash scripts/test.sh"
    assert "```bash\nbash scripts/test.sh\n```" in _text(README)


def _glaciar_commands(path: Path):
    """Every `glaciar ...` command line in the page's ```bash blocks, comments removed."""
    for block in re.findall(r"^```bash\n(.*?)^```", _text(path), re.S | re.M):
        for line in block.splitlines():
            for part in line.split("&&"):
                words = shlex.split(part, comments=True)
                if words and Path(words[0]).name == "glaciar":
                    yield words[1:]


COMMANDS = [(p, argv) for p in PAGES for argv in _glaciar_commands(p)]


@pytest.mark.parametrize("page,argv", COMMANDS,
                         ids=[f"{p.name}:{' '.join(a[:2])}" for p, a in COMMANDS])
def test_documented_commands_parse(page, argv, capsys):
    # Every command the pages show is accepted by the parser (sub-command and options exist).
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{page.name}: glaciar {' '.join(argv)}: {capsys.readouterr().err.strip()} "
                    f"(exit {exc.code})")


def test_readme_has_the_newcomer_sections():
    headings = set(_HEADING.findall(_prose(README)))
    for h in ("The two commands", "Expected run times", "Using it on your own survey, step by step",
              "Reading the selection function", "Where to go next"):
        assert h in headings, f"README.md: no section {h!r}"
    text = _text(README)
    assert "selection: []" in text                     # the detection-only example
    assert "maglim_f125w - mag_f160w > 1.5" in text    # the dropout example


# Python names the pages cite (`glaciar.store.read_results`, ...): they must exist, so a moved
# function shows up here rather than as a dead pointer in the docs.
_PY_NAME = re.compile(r"(?<![\w/.-])glaciar(?:\.[A-Za-z_]\w*)+")
#: dotted names in the pages that are not Python objects (Parquet footer keys)
_NOT_PYTHON = {"glaciar.mobs_hist"}


def _resolve(dotted: str):
    """Import the longest module prefix of ``dotted`` and get the rest as attributes."""
    import importlib

    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ModuleNotFoundError:
            continue
        for attr in parts[k:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(dotted)


@pytest.mark.parametrize("page", PAGES, ids=[p.relative_to(ROOT).as_posix() for p in PAGES])
def test_cited_python_names_exist(page):
    names = {n.removesuffix(".md") for n in _PY_NAME.findall(_text(page))} - _NOT_PYTHON
    missing = []
    for name in sorted(n for n in names if n != "glaciar"):
        try:
            _resolve(name)
        except (ImportError, AttributeError) as exc:
            missing.append(f"{name} ({exc})")
    assert not missing, f"{page.relative_to(ROOT)} cites names that do not exist: {missing}"
