"""The repository stands alone: no tracked file refers to a path outside the clone, such as a folder beside it."""
import os
import re
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))  # the checkout, also under Bazel
CHECKED_SUFFIXES = (".py", ".sh", ".yaml", ".md", "Makefile", "run", ".bzl", "BUILD", "WORKSPACE", ".bazelrc")
PARENT_PATH = re.compile(r"(?<![.\w])(?:\.\./)+[\w.-]+")  # ../x, ../../x (not .../x)


def escaping_paths(rel: str, text: str) -> list[str]:
    """The `../` paths in `text` (of the tracked file `rel`) that lead out of the repository."""
    here = os.path.dirname(os.path.join(ROOT, rel))
    return [m for m in PARENT_PATH.findall(text)
            if os.path.relpath(os.path.normpath(os.path.join(here, m)), ROOT).startswith("..")]


def test_escaping_paths_are_found():
    # From tools/x.py, ../y stays inside (ROOT/y) while ../../y leaves the checkout; .../y is prose.
    assert escaping_paths("tools/x.py", "open('../y'), open('../../y'), see .../y") == ["../../y"]


def test_no_file_refers_outside_the_repository():
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    offenders = {}
    for rel in tracked:
        if rel.startswith("data/") or rel == "tests/test_layout.py" or not rel.endswith(CHECKED_SUFFIXES):
            continue
        with open(os.path.join(ROOT, rel), encoding="utf-8", errors="replace") as f:
            found = escaping_paths(rel, f.read())
        if found:
            offenders[rel] = found
    assert not offenders, f"paths outside the repository: {offenders}"


def test_av2_sample_is_in_tree_with_its_notice():
    log = os.path.join(ROOT, "data", "av2_sample_log")
    assert os.path.isfile(os.path.join(log, "NOTICE.md"))
    assert len(os.listdir(os.path.join(log, "sensors", "lidar"))) == 2
