"""The Markdown documents' relative links: every file of the repository they point at exists and
every #anchor names a heading of its document (GitHub's slugs), so moving a file or renaming a
heading cannot silently break a reference; and every repository path the documents quote as code
(`bench/studies/long_hold.py`) still exists."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")
# a code span that is one path under a top-level folder of the repository (not `git show REV:path`)
CODE_PATH = re.compile(r"`((?:bench|docs|fem_ref|kernels|tests|warpgnn)/[\w./-]*)`")


def slug(title: str) -> str:
    """GitHub's heading anchor: lower case, punctuation but - and _ dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out, seen, fenced = set(), {}, False
    for line in path.read_text().splitlines():
        fenced ^= line.startswith("```")
        m = None if fenced else re.match(r"#+ (.*)", line)
        if m:
            s = slug(m.group(1))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
    return out


def test_slug_follows_github():
    assert slug("Vanilla with `--rotate` (bench/results/a_b.json)") == "vanilla-with---rotate-benchresultsa_bjson"
    assert slug("Ground truth (fem_ref)") == "ground-truth-fem_ref"


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: p.name)
def test_relative_links_resolve(document):
    broken = []
    for target in LINK.findall(document.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # http(s), mailto: not checked offline
        file_part, _, anchor = target.partition("#")
        path = (document.parent / file_part).resolve() if file_part else document
        if not path.is_relative_to(ROOT):
            continue  # outside the repository (the shared DESIGN.md): not part of a clone
        if not path.exists():
            broken.append(target)
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            broken.append(target)
    assert not broken, f"{document.name}: broken links {broken}"


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: p.name)
def test_quoted_paths_exist(document):
    missing = [p for p in CODE_PATH.findall(document.read_text()) if not (ROOT / p).exists()]
    assert not missing, f"{document.name}: quoted paths that are not in the repository {missing}"


def test_code_path_pattern():
    text = "run `bench/studies/long_hold.py`, not `git show ae2f903:bench/initial_loss.py` nor `bench/x.py --y`"
    assert CODE_PATH.findall(text) == ["bench/studies/long_hold.py"]


def test_readme_stays_a_short_guide():
    """The README is a user's guide (issue 55: at most 12 kB); the detail belongs in docs/."""
    assert len((ROOT / "README.md").read_bytes()) <= 12_000
