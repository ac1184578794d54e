"""Writing BUILD files: the stanzas to paste for missing targets, and the rewrite of the owned BUILD files (--fix)."""
from __future__ import annotations

import os

from bazel.targets.build_files import Workspace, absolute_label
from bazel.targets.expected import PYTEST_LOAD, RULES_WITH_SOURCES, Expected, Tree, owned

DERIVED = ("rule", "name", "srcs", "deps", "data", "fast", "slow")  # attributes computed from the sources
VISIBILITY = 'package(default_visibility = ["//visibility:public"])'


def stanzas_by_build_file(root: str, missing: list[Expected]) -> dict[str, str]:
    """{BUILD path: text to add} for the missing targets (with the header a new BUILD file needs)."""
    grouped: dict[str, list[Expected]] = {}
    for exp in missing:
        grouped.setdefault(f"{exp.package}/BUILD", []).append(exp)
    out = {}
    for path, exps in grouped.items():
        full = os.path.join(root, path)
        existing = _read(full)
        needs_load = any(e.rule == "pytest_test" for e in exps) and (existing is None or "pytest_test" not in existing)
        parts = []
        if existing is None:
            parts.append("\n".join(([PYTEST_LOAD, ""] if needs_load else []) + [VISIBILITY]))
        elif needs_load:
            parts.append(f"# add at the top: {PYTEST_LOAD}")
        out[path] = "\n\n".join(parts + [e.stanza() for e in exps]) + "\n"
    return out


def _read(path: str) -> str | None:
    """The text of `path`, None when there is no such file."""
    if not os.path.exists(path):
        return None
    with open(path, encoding="utf-8") as f:
        return f.read()


def _header(path: str) -> list[str]:
    """The comment lines at the top of an existing BUILD file."""
    lines = []
    for line in (_read(path) or "").split("\n"):
        if not line.startswith("#"):
            break
        lines.append(line)
    return lines


def _build_text(path: str, exps: list[Expected], existing: dict[str, dict], keep: set[str]) -> str:
    """The BUILD file of one package: its top comment, load and package lines, then a stanza per target of `exps`.

    Per target, the attributes not derived from the sources (timeout, tags, ...) are kept from `existing`, and so
    are the labels of its data (and, for a test, its deps) that are in `keep`.
    """
    pkg = exps[0].package
    stanzas = []
    for exp in exps:
        old = existing.get(exp.name, {})
        exp.extra = {k: v for k, v in old.items() if k not in DERIVED}
        exp.data |= {absolute_label(d, pkg) for d in old.get("data", [])} & keep
        if exp.rule == "pytest_test":  # a test may need a target it does not import (e.g. for a subprocess)
            exp.deps |= {absolute_label(d, pkg) for d in old.get("deps", [])} & keep
        stanzas.append(exp.stanza())
    head = _header(path)
    if any(e.rule == "pytest_test" for e in exps):
        head = head + ([""] if head else []) + [PYTEST_LOAD]
    head = head + ([""] if head else []) + [VISIBILITY]
    return "\n\n".join(["\n".join(head)] + stanzas) + "\n"


def fix(root: str) -> tuple[list[str], list[str]]:
    """Rewrite the BUILD files of the owned folders (expected.OWNED_DIRS) from the tree: (files written, problems left).

    Each file keeps its leading comment and, per target, attributes this checker does not derive (timeout, tags, ...).
    Targets whose source is gone are dropped. A file holding other kinds of targets (a filegroup, ...), or one that
    cannot be read, is left alone.
    """
    workspace = Workspace(root)
    packages, problems = workspace.packages, list(workspace.errors)
    by_package: dict[str, list[Expected]] = {}
    for exp in Tree(root).expected():
        if exp.fast or exp.slow:
            by_package.setdefault(exp.package, []).append(exp)
    for pkg in packages:
        if owned(pkg):
            by_package.setdefault(pkg, [])
    # Labels worth keeping when a target lists more than its sources show (data, test deps): those that will exist.
    keep = {e.label for exps in by_package.values() for e in exps} | {
        f"//{pkg}:{name}" for pkg, targets in packages.items() if not owned(pkg) for name in targets}
    written = []
    for pkg, exps in sorted(by_package.items()):
        path = os.path.join(root, pkg, "BUILD")
        existing = packages.get(pkg, {})
        foreign = sorted(n for n, t in existing.items() if t["rule"] not in RULES_WITH_SOURCES)
        if pkg in workspace.unreadable:
            problems.append(f"{pkg}/BUILD not rewritten: it cannot be read")
        elif foreign:
            problems.append(f"{pkg}/BUILD not rewritten: it holds targets this checker does not write: {foreign}")
        elif not exps:
            problems.append(f"{pkg}/BUILD has no sources left; delete it")
        elif _read(path) != (text := _build_text(path, exps, existing, keep)):
            with open(path, "w", encoding="utf-8") as f:
                f.write(text)
            written.append(f"{pkg}/BUILD")
    return written, problems
