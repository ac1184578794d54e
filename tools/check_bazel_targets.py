"""Check that the Bazel BUILD files cover the tree, so that `bazel test //...` runs every test and cannot rot.

    python tools/check_bazel_targets.py                   # exit 1, listing every missing or outdated entry
    python tools/check_bazel_targets.py --print-missing   # also print the BUILD stanzas to paste
    python tools/check_bazel_targets.py --fix             # rewrite the BUILD files of ff3d_tf/, tools/, tests/

What it expects (targets are found by reading the BUILD files, not by running Bazel):
- ff3d_tf/**/*.py: a `py_library` per module (named after the module; `__init__.py` after its package folder), whose
  deps hold the target of every first-party module it imports, and no first-party target it does not import.
- tools/*.py: a `py_binary` per tool (`py_library` for helpers named `_*`), deps as above; `data` holds //configs when
  the tool names a configs/ file and the target of each tool it starts (a string naming `<tool>.py`).
- tests/**/test_*.py: a `pytest_test` (bazel/pytest.bzl) per file, with `fast` / `slow` saying whether the file has
  tests not marked / marked `@pytest.mark.slow`; deps hold what it imports (other test modules included) and `data`
  the configs, the in-tree Argoverse 2 sample and the tools that the file names. Other tests/**/*.py: a `py_library`.
Targets whose source file is gone are reported too.
"""
from __future__ import annotations

import argparse
import ast
import glob as globlib
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = "ff3d_tf"
FIRST_PARTY_DIRS = (PACKAGE, "tools", "tests")  # the folders whose BUILD files this checker writes
RULES_WITH_SOURCES = ("py_library", "py_binary", "py_test", "pytest_test")
CONFIGS = "//configs:configs"
AV2_SAMPLE = "//data:av2_sample_log"
# What a source names to need them; written in two parts so that this file does not name them itself.
CONFIGS_NEEDLE = "configs" + "/"
AV2_NEEDLE = "av2_" + "sample_log"
PYTEST_LOAD = 'load("//bazel:pytest.bzl", "pytest_test")'


# ----------------------------------------------------------------------------------------------------------------------
# Reading BUILD files

class BuildFileError(ValueError):
    """A BUILD file this checker cannot read (its message names the file and what is wrong)."""


def read_build_file(path: str, package_dir: str) -> dict[str, dict]:
    """Targets of one BUILD file: {name: {"rule": ..., "srcs": [...], "deps": [...], "data": [...], ...}}.

    BUILD files are Starlark; the subset used here (calls with keyword arguments, lists, strings, glob) is also Python,
    so the file is evaluated with a recorder in place of each rule. Nothing in it is imported or run otherwise.
    """
    targets: dict[str, dict] = {}

    def record(rule):
        def call(*args, **attrs):
            if "name" in attrs:
                if attrs["name"] in targets:
                    raise BuildFileError(f"{path}: target {attrs['name']!r} defined twice")
                targets[attrs["name"]] = {"rule": rule, **attrs}
        return call

    def glob(include, exclude=(), **_):
        found = set()
        for pattern in include:
            found.update(os.path.relpath(p, package_dir)
                         for p in globlib.glob(os.path.join(package_dir, pattern), recursive=True) if os.path.isfile(p))
        for pattern in exclude:
            found.difference_update(os.path.relpath(p, package_dir)
                                    for p in globlib.glob(os.path.join(package_dir, pattern), recursive=True))
        return sorted(found)

    class Namespace(dict):
        def __missing__(self, key):  # any rule or macro not named below records its targets too
            return record(key)

    namespace = Namespace(glob=glob, load=lambda *a, **k: None, package=lambda **k: None,
                          exports_files=lambda *a, **k: None, select=lambda d: d.get("//conditions:default", []))
    with open(path, encoding="utf-8") as f:
        text = f.read()
    try:
        exec(compile(text, path, "exec"), {"__builtins__": {"True": True, "False": False, "None": None}}, namespace)
    except BuildFileError:
        raise
    except Exception as e:  # noqa: BLE001 - a BUILD file this reader cannot evaluate is reported, not guessed at
        raise BuildFileError(f"{path}: cannot read ({type(e).__name__}: {e})") from e
    return targets


def bazel_ignored(root: str) -> list[str]:
    path = os.path.join(root, ".bazelignore")
    if not os.path.exists(path):
        return []
    with open(path, encoding="utf-8") as f:
        return [line.strip().strip("/") for line in f if line.strip() and not line.startswith("#")]


def read_workspace(root: str) -> tuple[dict[str, dict[str, dict]], list[str]]:
    """{package: targets} of every BUILD file outside .bazelignore'd folders, and the errors met reading them."""
    ignored = set(bazel_ignored(root))
    packages, errors = {}, []
    for dirpath, dirnames, filenames in os.walk(root):
        rel = os.path.relpath(dirpath, root).replace(os.sep, "/")
        rel = "" if rel == "." else rel
        dirnames[:] = sorted(d for d in dirnames
                             if not d.startswith((".", "bazel-")) and f"{rel}/{d}".strip("/") not in ignored)
        if "BUILD" in filenames or "BUILD.bazel" in filenames:
            name = "BUILD" if "BUILD" in filenames else "BUILD.bazel"
            try:
                packages[rel] = read_build_file(os.path.join(dirpath, name), dirpath)
            except BuildFileError as e:
                errors.append(str(e))
                packages[rel] = {}
    return packages, errors


def absolute_label(label: str, package: str) -> str:
    """`//pkg:name` for `:name`, `name`, `//pkg` or `//pkg:name` written in `package`."""
    if label.startswith("@"):
        return label
    if label.startswith("//"):
        pkg, _, name = label[2:].partition(":")
        return f"//{pkg}:{name or pkg.rsplit('/', 1)[-1]}"
    return f"//{package}:{label.lstrip(':')}"


def short_label(label: str, package: str) -> str:
    """The way a BUILD file in `package` writes an absolute `//pkg:name`."""
    pkg, _, name = label[2:].partition(":")
    if pkg == package:
        return f":{name}"
    return f"//{pkg}" if pkg.rsplit("/", 1)[-1] == name else label


# ----------------------------------------------------------------------------------------------------------------------
# What the sources need

def _parse(path: str) -> ast.Module:
    with open(path, encoding="utf-8") as f:
        return ast.parse(f.read(), filename=path)


def imported_modules(tree: ast.Module, module: str, is_package: bool, is_module=lambda name: False) -> set[str]:
    """Absolute names of the modules `tree` imports (also inside functions).

    `from a import b` gives a.b when `is_module("a.b")`, else a. Importing a.b also runs the __init__ of package a;
    Bazel's runfiles hold that __init__ only when a target names it, and only the module named is a dep.
    """
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".")
                parts = parts if is_package else parts[:-1]
                parts = parts[:len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            names.update(f"{base}.{alias.name}" if is_module(f"{base}.{alias.name}") else base
                         for alias in node.names)
    return names


def string_constants(tree: ast.Module) -> list[str]:
    """The string literals of `tree`, docstrings left out (they name files as examples, not as inputs)."""
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body
                  and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return [node.value for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings]


def _is_slow_mark(node: ast.AST, aliases: set[str]) -> bool:
    """`pytest.mark.slow`, `mark.slow`, a call of either, or a module-level alias of one."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Name):
        return node.id in aliases
    return isinstance(node, ast.Attribute) and node.attr == "slow" and "mark" in ast.unparse(node.value)


def _marks_slow(node: ast.AST, aliases: set[str]) -> bool:
    """A `pytestmark = ...` value or `marks=` argument that is or lists the slow mark."""
    items = node.elts if isinstance(node, (ast.List, ast.Tuple)) else [node]
    return any(_is_slow_mark(item, aliases) for item in items)


def _parametrize_split(decorator: ast.AST, aliases: set[str]) -> tuple[bool, bool]:
    """(has fast cases, has slow cases) of a `@pytest.mark.parametrize(..., [cases])` decorator."""
    if not (isinstance(decorator, ast.Call) and len(decorator.args) >= 2
            and isinstance(decorator.args[1], (ast.List, ast.Tuple))):
        return True, False
    fast = slow = False
    for case in decorator.args[1].elts:
        case_slow = (isinstance(case, ast.Call) and ast.unparse(case.func).endswith("param")
                     and any(k.arg == "marks" and _marks_slow(k.value, aliases) for k in case.keywords))
        slow, fast = slow or case_slow, fast or not case_slow
    return fast, slow


def speed_split(tree: ast.Module) -> tuple[bool, bool]:
    """(has tests not marked slow, has tests marked slow) of a pytest module."""
    aliases = {t.id for node in tree.body if isinstance(node, ast.Assign) and _is_slow_mark(node.value, set())
               for t in node.targets if isinstance(t, ast.Name)}
    module_slow = any(isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in node.targets)
                      and _marks_slow(node.value, aliases) for node in tree.body)
    fast = slow = False

    def visit(functions, inherited_slow):
        nonlocal fast, slow
        for fn in functions:
            if not (isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) and fn.name.startswith("test")):
                continue
            fn_fast, fn_slow = True, False
            if inherited_slow or any(_is_slow_mark(d, aliases) for d in fn.decorator_list):
                fn_fast, fn_slow = False, True
            else:
                for d in fn.decorator_list:
                    if isinstance(d, ast.Call) and ast.unparse(d.func).endswith("parametrize"):
                        case_fast, case_slow = _parametrize_split(d, aliases)
                        fn_fast, fn_slow = fn_fast and case_fast, fn_slow or case_slow
            fast, slow = fast or fn_fast, slow or fn_slow

    visit(tree.body, module_slow)
    for cls in tree.body:
        if isinstance(cls, ast.ClassDef) and cls.name.startswith("Test"):
            cls_slow = module_slow or any(_is_slow_mark(d, aliases) for d in cls.decorator_list) or any(
                isinstance(n, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in n.targets)
                and _marks_slow(n.value, aliases) for n in cls.body)
            visit(cls.body, cls_slow)
    return fast, slow


class Expected:
    """The target one source file needs."""

    def __init__(self, path, package, name, rule, deps=(), data=(), fast=True, slow=False):
        self.path, self.package, self.name, self.rule = path, package, name, rule
        self.deps, self.data, self.fast, self.slow = set(deps), set(data), fast, slow
        self.extra: dict = {}  # attributes kept from the existing target (timeout, tags, ...)

    @property
    def label(self):
        return f"//{self.package}:{self.name}"

    def stanza(self) -> str:
        lines = [f"{self.rule}(", f'    name = "{self.name}",']
        if self.rule != "pytest_test":
            lines.append(f'    srcs = ["{os.path.basename(self.path)}"],')
        for attr in ("data", "deps"):
            labels = sorted((short_label(label, self.package) for label in getattr(self, attr)),
                            key=lambda s: (not s.startswith(":"), s))
            if len(labels) == 1:
                lines.append(f'    {attr} = ["{labels[0]}"],')
            elif labels:
                lines += [f"    {attr} = ["] + [f'        "{label}",' for label in labels] + ["    ],"]
        if self.rule == "pytest_test":
            if not self.fast:
                lines.append("    fast = False,")
            if self.slow:
                lines.append("    slow = True,")
        lines += [f"    {key} = {_starlark(value)}," for key, value in self.extra.items()]
        return "\n".join(lines + [")"])


class Tree:
    """The first-party Python files of a checkout and the Bazel target each one needs."""

    def __init__(self, root: str):
        self.root = root
        self.errors: list[str] = []  # sources that do not parse

    def parse(self, path: str) -> ast.Module | None:
        try:
            return _parse(os.path.join(self.root, path))
        except (SyntaxError, UnicodeDecodeError) as e:
            self.errors.append(f"{path}: cannot parse ({e})")
            return None

    def rel(self, path):
        return os.path.relpath(path, self.root).replace(os.sep, "/")

    def files(self, top: str, pattern: str = "**/*.py") -> list[str]:
        found = globlib.glob(os.path.join(self.root, top, pattern), recursive=True)
        return sorted(self.rel(p) for p in found if "__pycache__" not in p and os.path.isfile(p))

    def library_label(self, module: str) -> str | None:
        """The target of first-party module `module` (dotted), or None when it is not a file of this tree."""
        path = module.replace(".", "/")
        if os.path.isfile(os.path.join(self.root, path + ".py")):
            package, _, name = path.rpartition("/")
            return f"//{package}:{name}"
        if os.path.isfile(os.path.join(self.root, path, "__init__.py")):
            return f"//{path}:{path.rsplit('/', 1)[-1]}"
        return None

    def first_party_deps(self, tree, module, is_package, own_label, local_dirs=()) -> set[str]:
        """Targets of the first-party modules that `tree` imports; `local_dirs` hold modules imported by bare name."""
        deps = set()
        for name in imported_modules(tree, module, is_package,
                                     lambda n: os.path.isfile(os.path.join(self.root, n.replace(".", "/") + ".py"))):
            label = None
            if name.split(".")[0] in FIRST_PARTY_DIRS and (name == PACKAGE or "." in name):
                label = self.library_label(name)  # ff3d_tf..., or tests.x.y (the checkout's root is on sys.path)
            elif "." not in name:
                for d in local_dirs:
                    if os.path.isfile(os.path.join(self.root, d, name + ".py")):
                        label = f"//{d}:{name}"
                        break
            if label and label != own_label:
                deps.add(label)
        return deps

    def data_needs(self, tree) -> set[str]:
        """//configs, the Argoverse 2 sample and the tools that the strings and names of `tree` refer to."""
        data = set()
        texts = string_constants(tree)
        names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
            a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) for a in n.names}
        if any(CONFIGS_NEEDLE in t for t in texts):
            data.add(CONFIGS)
        if "AV2_LOG" in names or any(AV2_NEEDLE in t for t in texts):
            data.add(AV2_SAMPLE)
        for tool in self.files("tools", "*.py"):
            stem = os.path.basename(tool)
            if any(t == stem or t.endswith("/" + stem) for t in texts):
                data.add(f"//tools:{stem[:-3]}")
        return data

    def expected(self) -> list[Expected]:
        out = []
        for path in self.files(PACKAGE):
            package, base = os.path.dirname(path), os.path.basename(path)
            is_package = base == "__init__.py"
            name = package.rsplit("/", 1)[-1] if is_package else base[:-3]
            module = package.replace("/", ".") + ("" if is_package else "." + name)
            label = f"//{package}:{name}"
            tree = self.parse(path)
            if tree is None:
                continue
            out.append(Expected(path, package, name, "py_library",
                                self.first_party_deps(tree, module, is_package, label)))
        for path in self.files("tools", "*.py"):
            name = os.path.basename(path)[:-3]
            tree = self.parse(path)
            if tree is None:
                continue
            label = f"//tools:{name}"
            deps = self.first_party_deps(tree, name, False, label, local_dirs=["tools"])
            data = self.data_needs(tree) - {label}
            rule = "py_library" if name.startswith("_") else "py_binary"
            out.append(Expected(path, "tools", name, rule, deps, data if rule == "py_binary" else ()))
        for path in self.files("tests"):
            package, base = os.path.dirname(path), os.path.basename(path)
            name = base[:-3]
            tree = self.parse(path)
            if tree is None:
                continue
            label = f"//{package}:{name}"
            local_dirs = [package] + (["tests"] if package != "tests" else [])
            deps = self.first_party_deps(tree, name, False, label, local_dirs)
            if base.startswith("test_"):
                fast, slow = speed_split(tree)
                deps.discard("//tests:conftest")  # every pytest_test gets it
                out.append(Expected(path, package, name, "pytest_test", deps, self.data_needs(tree), fast, slow))
            else:
                out.append(Expected(path, package, name, "py_library", deps))
        return out


# ----------------------------------------------------------------------------------------------------------------------
# Comparing

def check(root: str) -> tuple[list[str], list[Expected], list[tuple[Expected, str]]]:
    """(problems, missing targets, (expected, problem) of existing targets that differ)."""
    packages, problems = read_workspace(root)
    tree = Tree(root)
    expected = tree.expected()
    problems += tree.errors
    defined = {f"//{pkg}:{name}" for pkg, targets in packages.items() for name in targets}
    missing, wrong = [], []
    seen: dict[str, str] = {}
    for exp in expected:
        if exp.label in seen:
            problems.append(f"{exp.path} and {seen[exp.label]} both need the target {exp.label}; rename one")
        seen[exp.label] = exp.path
    for exp in expected:
        if not exp.fast and not exp.slow:
            problems.append(f"{exp.path}: no test functions")
            continue
        targets = packages.get(exp.package)
        build = f"{exp.package}/BUILD"
        if targets is None:
            problems.append(f"{exp.path}: no {build} (a {exp.rule} {exp.name!r} is needed)")
            missing.append(exp)
            continue
        target = targets.get(exp.name)
        if target is None:
            problems.append(f"{exp.path}: no {exp.rule} {exp.name!r} in {build}")
            missing.append(exp)
            continue
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
        first_party = {d for d in have_deps if d.startswith(("//ff3d_tf", "//tools", "//tests"))}
        if exp.rule != "pytest_test" and first_party - exp.deps:
            diffs.append("deps name modules it does not import: " + ", ".join(sorted(first_party - exp.deps)))
        if exp.data - have_data:
            diffs.append("data lack " + ", ".join(sorted(exp.data - have_data)))
        if exp.rule == "pytest_test":
            fast, slow = target.get("fast", True), target.get("slow", False)
            if (fast, slow) != (exp.fast, exp.slow):
                diffs.append(f"has fast = {fast}, slow = {slow}; the file needs fast = {exp.fast}, slow = {exp.slow}")
        for d in diffs:
            problems.append(f"{exp.path}: {build} target {exp.name!r} {d}")
        if diffs:
            wrong.append((exp, "; ".join(diffs)))
    # Targets whose sources are gone, and labels that name no target or file.
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
    return problems, missing, wrong


def stanzas_by_build_file(root: str, missing: list[Expected]) -> dict[str, str]:
    """{BUILD path: text to add} for the missing targets (with the header a new BUILD file needs)."""
    grouped: dict[str, list[Expected]] = {}
    for exp in missing:
        grouped.setdefault(f"{exp.package}/BUILD", []).append(exp)
    out = {}
    for path, exps in grouped.items():
        full = os.path.join(root, path)
        existing = open(full, encoding="utf-8").read() if os.path.exists(full) else None
        needs_load = any(e.rule == "pytest_test" for e in exps) and (existing is None or "pytest_test" not in existing)
        parts = []
        if existing is None:
            parts.append("\n".join(([PYTEST_LOAD, ""] if needs_load else [])
                                   + ['package(default_visibility = ["//visibility:public"])']))
        elif needs_load:
            parts.append(f"# add at the top: {PYTEST_LOAD}")
        out[path] = "\n\n".join(parts + [e.stanza() for e in exps]) + "\n"
    return out


def _starlark(value) -> str:
    if isinstance(value, bool) or value is None:
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_starlark(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_starlark(k)}: {_starlark(v)}" for k, v in value.items()) + "}"
    return json.dumps(value) if isinstance(value, str) else repr(value)


def _header(path: str) -> list[str]:
    """The comment lines at the top of an existing BUILD file."""
    if not os.path.exists(path):
        return []
    lines = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if not line.startswith("#"):
                break
            lines.append(line.rstrip("\n"))
    return lines


def fix(root: str) -> tuple[list[str], list[str]]:
    """Rewrite the BUILD files of ff3d_tf/, tools/ and tests/ from the tree: (files written, problems left).

    Each file keeps its leading comment and, per target, attributes this checker does not derive (timeout, tags, ...).
    Targets whose source is gone are dropped. A file holding other kinds of targets (a filegroup, ...) is left alone.
    """
    packages, problems = read_workspace(root)
    by_package: dict[str, list[Expected]] = {}
    for exp in Tree(root).expected():
        if exp.fast or exp.slow:
            by_package.setdefault(exp.package, []).append(exp)
    for pkg in packages:
        if pkg.split("/")[0] in FIRST_PARTY_DIRS:
            by_package.setdefault(pkg, [])
    # Labels worth keeping when a target lists more than its sources show (data, test deps): those that will exist.
    keep = {e.label for exps in by_package.values() for e in exps} | {
        f"//{pkg}:{name}" for pkg, targets in packages.items() if pkg.split("/")[0] not in FIRST_PARTY_DIRS
        for name in targets}
    written = []
    for pkg, exps in sorted(by_package.items()):
        path = os.path.join(root, pkg, "BUILD")
        existing = packages.get(pkg, {})
        foreign = sorted(n for n, t in existing.items() if t["rule"] not in RULES_WITH_SOURCES)
        if foreign:
            problems.append(f"{pkg}/BUILD not rewritten: it holds targets this checker does not write: {foreign}")
            continue
        stanzas = []
        for exp in exps:
            old = existing.get(exp.name, {})
            exp.extra = {k: v for k, v in old.items() if k not in ("rule", "name", "srcs", "deps", "data", "fast", "slow")}
            exp.data |= {absolute_label(d, pkg) for d in old.get("data", [])} & keep
            if exp.rule == "pytest_test":  # a test may need a target it does not import (e.g. for a subprocess)
                exp.deps |= {absolute_label(d, pkg) for d in old.get("deps", [])} & keep
            stanzas.append(exp.stanza())
        if not stanzas:
            problems.append(f"{pkg}/BUILD has no sources left; delete it")
            continue
        head = _header(path)
        if any(e.rule == "pytest_test" for e in exps):
            head = head + ([""] if head else []) + [PYTEST_LOAD]
        head = head + ([""] if head else []) + ['package(default_visibility = ["//visibility:public"])']
        text = "\n\n".join(["\n".join(head)] + stanzas) + "\n"
        if not os.path.exists(path) or open(path, encoding="utf-8").read() != text:
            with open(path, "w", encoding="utf-8") as f:
                f.write(text)
            written.append(f"{pkg}/BUILD")
    return written, problems


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", default=ROOT, help="checkout to check (default: this one)")
    p.add_argument("--print-missing", action="store_true", help="print the BUILD stanzas that would fix the problems")
    p.add_argument("--fix", action="store_true",
                   help="rewrite the BUILD files of ff3d_tf/, tools/, tests/ to match the tree (keeps comments at the "
                        "top and attributes it does not derive, such as timeout or tags)")
    args = p.parse_args(argv)
    root = os.path.abspath(args.root)
    problems, missing, wrong = check(root)
    if args.fix:
        written, left = fix(root)
        for path in written:
            print(f"rewrote {path}")
        for problem in left:
            print(f"  not fixed: {problem}", file=sys.stderr)
        problems, missing, wrong = check(root)
    if not problems:
        print(f"Bazel targets cover the tree ({len(Tree(root).expected())} source files)")
        return 0
    print(f"{len(problems)} problem(s) with the Bazel BUILD files:", file=sys.stderr)
    for problem in problems:
        print(f"  {problem}", file=sys.stderr)
    if args.print_missing:
        for path, text in stanzas_by_build_file(root, missing).items():
            print(f"\n# ---- add to {path}\n{text}", end="")
        for exp, why in wrong:
            print(f"\n# ---- replace {exp.name!r} in {exp.package}/BUILD ({why})\n{exp.stanza()}")
    else:
        print("run with --print-missing for the stanzas to paste", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
