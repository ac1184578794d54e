"""The differences between the targets the sources need (expected.Tree) and the BUILD files (build_files.Workspace)."""
from __future__ import annotations

import os

from bazel.targets.build_files import Workspace, absolute_label
from bazel.targets.expected import RULES_WITH_SOURCES, Expected, Tree, owned


def check(root: str) -> tuple[list[str], list[Expected], list[tuple[Expected, str]]]:
    """(problems, missing targets, (expected, problem) of existing targets that differ) of the checkout `root`."""
    workspace = Workspace(root)
    tree = Tree(root)
    expected = tree.expected()
    problems = workspace.errors + tree.errors
    missing, wrong = [], []
    seen: dict[str, str] = {}
    for exp in expected:
        if exp.label in seen:
            problems.append(f"{exp.path} and {seen[exp.label]} both need the target {exp.label}; rename one")
        seen[exp.label] = exp.path
    for exp in expected:
        build = f"{exp.package}/BUILD"
        targets = workspace.packages.get(exp.package)
        if not exp.fast and not exp.slow:
            problems.append(f"{exp.path}: no test functions")
        elif exp.package in workspace.unreadable:
            continue  # its read error is the problem
        elif targets is None:
            problems.append(f"{exp.path}: no {build} (a {exp.rule} {exp.name!r} is needed)")
            missing.append(exp)
        elif exp.name not in targets:
            problems.append(f"{exp.path}: no {exp.rule} {exp.name!r} in {build}")
            missing.append(exp)
        elif diffs := _differences(exp, targets[exp.name]):
            problems += [f"{exp.path}: {build} target {exp.name!r} {d}" for d in diffs]
            wrong.append((exp, "; ".join(diffs)))
    return problems + _dangling(root, workspace.packages) + _cycles(workspace.packages), missing, wrong


def _differences(exp: Expected, target: dict) -> list[str]:
    """What the existing `target` lacks or has too much compared with `exp`."""
    base = os.path.basename(exp.path)
    diffs = []
    if target["rule"] != exp.rule:
        diffs.append(f"is a {target['rule']}, expected {exp.rule}")
    if exp.rule != "pytest_test" and base not in target.get("srcs", []):
        diffs.append(f"srcs lack {base}")
    have_deps = {absolute_label(d, exp.package) for d in target.get("deps", [])}
    have_data = {absolute_label(d, exp.package) for d in target.get("data", [])}
    if exp.deps - have_deps:
        diffs.append("deps lack " + ", ".join(sorted(exp.deps - have_deps)))
    first_party = {d for d in have_deps if d.startswith("//") and owned(d[2:].partition(":")[0])}
    if exp.rule != "pytest_test" and first_party - exp.deps:
        diffs.append("deps name modules it does not import: " + ", ".join(sorted(first_party - exp.deps)))
    if exp.data - have_data:
        diffs.append("data lack " + ", ".join(sorted(exp.data - have_data)))
    if exp.rule == "pytest_test":
        fast, slow = target.get("fast", True), target.get("slow", False)
        if (fast, slow) != (exp.fast, exp.slow):
            diffs.append(f"has fast = {fast}, slow = {slow}; the file needs fast = {exp.fast}, slow = {exp.slow}")
    return diffs


def _dangling(root: str, packages: dict[str, dict[str, dict]]) -> list[str]:
    """Targets whose sources are gone, and labels that name no target or file."""
    defined = {f"//{pkg}:{name}" for pkg, targets in packages.items() for name in targets}
    problems = []
    for pkg, targets in sorted(packages.items()):
        for name, target in sorted(targets.items()):
            if target["rule"] not in RULES_WITH_SOURCES:
                continue
            srcs = target.get("srcs") or ([f"{name}.py"] if target["rule"] == "pytest_test" else [])
            for src in srcs:
                if not src.startswith("//") and not os.path.isfile(os.path.join(root, pkg, src)):
                    problems.append(f"{pkg}/BUILD target {name!r}: source {pkg}/{src} does not exist")
            for label in list(target.get("deps", [])) + list(target.get("data", [])):
                full = absolute_label(label, pkg)
                lpkg, _, lname = full[2:].partition(":")
                if full.startswith("//") and full not in defined and not os.path.isfile(
                        os.path.join(root, lpkg, lname)):
                    problems.append(f"{pkg}/BUILD target {name!r}: {label} names no target")
    return problems



def _cycles(packages: dict[str, dict[str, dict]]) -> list[str]:
    """Each cycle of first-party deps, named by its labels (Bazel refuses to analyse any target above one: a module
    importing another lazily, inside a function, still needs it as a dep)."""
    graph = {f"//{pkg}:{name}": [absolute_label(d, pkg) for d in target.get("deps", [])]
             for pkg, targets in packages.items() for name, target in targets.items()}
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []
    problems = []

    def visit(label: str) -> None:
        state[label] = 1
        path.append(label)
        for dep in graph.get(label, ()):
            if state.get(dep) == 1:
                problems.append("cycle in the deps: " + " -> ".join(path[path.index(dep):] + [dep]))
            elif dep in graph and dep not in state:
                visit(dep)
        path.pop()
        state[label] = 2

    for label in sorted(graph):
        if label not in state:
            visit(label)
    return problems
