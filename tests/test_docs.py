"""The repository's text speaks to users: no machine's folders, no numbered references to past work, no dead links.

Every tracked text file (*.md, *.py, *.json, *.toml, *.txt, *.sh) is read. Three rules:

1. no absolute path outside the repository: a user's or the superuser's home, a work or temporary folder at the
   file system's root, or a Windows drive (a command in the docs runs from a fresh clone: paths are relative to the
   repository or placeholders such as DIR);
2. no numbered reference to when a piece of work was done ("session" or "issue" followed by its number, a
   two-digit "s" tag, the phrase for such a period): history is dated, in CHANGELOG.md;
3. every ``scripts/``, ``research/`` or ``docs/`` path a file cites exists, and every relative Markdown link of a
   document points at a file of the repository.

In a test module only the comments and docstrings are prose: its code may make temporary folders of its own.
Everywhere else the whole file counts, defaults and help strings included.
"""

from __future__ import annotations

import ast
import io
import re
import subprocess
import tokenize
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TEXT_SUFFIXES = {".md", ".py", ".json", ".toml", ".txt", ".sh"}

# A root-level folder of one machine, not preceded by anything that makes it part of a longer relative path or URL.
ABSOLUTE = re.compile(r"(?<![\w.~/-])/(?:work|root|home|tmp)/|(?<![\w\\])[A-Za-z]:\\{1,2}[A-Za-z_]")
WORK_PERIOD = re.compile(r"\b(?:sessions?|issues?)\s+#?\d+|\bs[1-9]\d\b|\bwork[- ]periods?\b", re.IGNORECASE)
CITED = re.compile(r"(?<![\w./*-])((?:scripts|research|docs)/[\w-][\w./-]*)")
MD_LINK = re.compile(r"\]\(([^)\s]+)\)")

# Documents the README links to whose own text is written beside it; cited before they exist.
PLANNED = {"docs/training.md", "docs/game_engines.md"}


def tracked_text_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("needs a git checkout of the repository (git ls-files)")
    names = [n for n in out.decode().split("\0") if n]
    return [REPO / n for n in names if Path(n).suffix in TEXT_SUFFIXES and (REPO / n).is_file()]


def prose_of_python(text: str) -> list[tuple[int, str]]:
    """(line, text) of a module's comments and docstrings."""
    found = []
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            found.append((tok.start[0], tok.string))
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc is not None:
                found.append((node.body[0].lineno, doc))
    return found


def units(path: Path) -> list[tuple[int, str]]:
    """(line, text) pieces of a file that the rules apply to."""
    text = path.read_text(encoding="utf-8")
    rel = path.relative_to(REPO)
    if rel.parts[0] == "tests" and path.suffix == ".py":
        return prose_of_python(text)
    return list(enumerate(text.splitlines(), start=1))


def violations(pattern: re.Pattern) -> list[str]:
    bad = []
    for path in tracked_text_files():
        for line, text in units(path):
            for m in pattern.finditer(text):
                bad.append(f"{path.relative_to(REPO)}:{line}: {m.group(0)!r}")
    return bad


def test_no_absolute_path_of_a_machine():
    bad = violations(ABSOLUTE)
    assert not bad, f"{len(bad)} absolute paths outside the repository (use a relative path or DIR):\n" + "\n".join(
        bad[:40])


def test_no_numbered_work_period():
    bad = violations(WORK_PERIOD)
    assert not bad, f"{len(bad)} numbered work-period references (date the change in CHANGELOG.md):\n" + "\n".join(
        bad[:40])


def cited_paths(text: str) -> list[str]:
    return [m.group(1).rstrip(".") for m in CITED.finditer(text)]


def test_every_cited_script_research_and_doc_path_exists():
    missing = []
    for path in tracked_text_files():
        for line, text in units(path):
            for cited in cited_paths(text):
                if cited not in PLANNED and not (REPO / cited).exists():
                    missing.append(f"{path.relative_to(REPO)}:{line}: {cited}")
    assert not missing, f"{len(missing)} cited paths that are not in the repository:\n" + "\n".join(missing[:40])


def test_every_relative_markdown_link_points_into_the_repository():
    missing = []
    for path in tracked_text_files():
        if path.suffix != ".md":
            continue
        for line, text in units(path):
            for target in MD_LINK.findall(text):
                target = target.split("#")[0]
                if not target or "://" in target or target.startswith("mailto:"):
                    continue
                resolved = (path.parent / target).resolve()
                rel = resolved.relative_to(REPO).as_posix() if resolved.is_relative_to(REPO) else target
                if rel not in PLANNED and not resolved.exists():
                    missing.append(f"{path.relative_to(REPO)}:{line}: {target}")
    assert not missing, f"{len(missing)} Markdown links to missing files:\n" + "\n".join(missing[:40])


@pytest.mark.parametrize("text, rule", [
    ("python x.py --data /work/data/bandai", ABSOLUTE),
    ('default=Path("/root/runs")', ABSOLUTE),
    ("see C:\\Users\\me\\mocap", ABSOLUTE),
    ("written under /tmp/v21.json", ABSOLUTE),
    ("measured in session 33", WORK_PERIOD),
    ("the gate of issue 15", WORK_PERIOD),
    ("(issue 18)", WORK_PERIOD),
    ("the probe in proto/s32/x.py", WORK_PERIOD),
    ("this work period's runs", WORK_PERIOD),
])
def test_the_rules_catch_what_they_name(text, rule):
    assert rule.search(text)


@pytest.mark.parametrize("text, rule", [
    ("python -m mld_core data prepare bvh ~/mocap --out data/mine", ABSOLUTE),
    ("../shared/datasets/cmu-subsets.tar.xz", ABSOLUTE),
    ("https://example.org/work/x", ABSOLUTE),
    ("s1, s2 = split(a), split(b)", WORK_PERIOD),
    ("tr sqrt(S1 S2)", WORK_PERIOD),
    ("one session of Blender", WORK_PERIOD),
])
def test_the_rules_leave_ordinary_text_alone(text, rule):
    assert not rule.search(text)


def test_cited_paths_are_read_whole():
    text = "run `python scripts/side_accuracy.py --data DIR`; see docs/draft.md#the-draft and docs/*.md."
    assert cited_paths(text) == ["scripts/side_accuracy.py", "docs/draft.md"]
    assert cited_paths('sorted(base.glob("*/scripts/addons_core/x.py"))') == []
