"""The Bazel target that each first-party source file needs, derived from its syntax tree, and its BUILD stanza.

- ff3d_tf/**/*.py, lab/**/*.py (but lab/tools/) and bazel/targets/*.py: a `py_library` per module (named after the
  module; `__init__.py` after its package folder), whose deps hold the target of every first-party module it imports.
- tools/*.py and lab/tools/*.py: a `py_binary` per tool (`py_library` for helpers named `_*`), deps as above (a lab
  tool's bare `import _common` is tools/_common.py); `data` holds //configs when the tool names a configs/ file and
  the target of each tool it starts (a string naming `<tool>.py`).
- tests/**/test_*.py: a `pytest_test` (bazel/pytest.bzl) per file, with `fast` / `slow` saying whether the file has
  tests not marked / marked `@pytest.mark.slow`; deps hold what it imports (other test modules included) and `data`
  the configs, the in-tree Argoverse 2 sample and the tools that the file names. Other tests/**/*.py: a `py_library`
  with the same `data` (conftest's fixtures read the sample for every test that uses them).
"""
from __future__ import annotations

import ast
import glob as globlib
import json
import os

from bazel.targets.build_files import short_label
from bazel.targets.sources import imported_modules, parse, speed_split, string_constants

PACKAGE = "ff3d_tf"
LAB = "lab"  # the studies, benchmarks and profilers: never imported by ff3d_tf (tests/test_layout.py)
PACKAGES = (PACKAGE, LAB)  # the first-party packages a bare `import <name>` may name
TOOL_DIRS = ("tools", "lab/tools")  # a py_binary per tool; each runs with its own folder and tools/ on sys.path
LIBRARY_DIRS = (PACKAGE, LAB, "bazel/targets")  # a py_library per module (but those of TOOL_DIRS)
OWNED_DIRS = LIBRARY_DIRS + ("tools", "tests")  # the folders (and their subfolders) whose BUILD files are written
RULES_WITH_SOURCES = ("py_library", "py_binary", "py_test", "pytest_test")
CONFIGS = "//configs:configs"
AV2_SAMPLE = "//data:av2_sample_log"
# What a source names to need them; written in two parts so that this file does not name them itself.
CONFIGS_NEEDLE = "configs" + "/"
AV2_NEEDLE = "av2_" + "sample_log"
PYTEST_LOAD = 'load("//bazel:pytest.bzl", "pytest_test")'


def owned(package: str) -> bool:
    """Whether the BUILD file of `package` (a folder relative to the checkout) is one this checker writes."""
    return any(package == d or package.startswith(d + "/") for d in OWNED_DIRS)


def starlark(value) -> str:
    """`value` (a literal read from a BUILD file) written as Starlark."""
    if isinstance(value, bool) or value is None:
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(starlark(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{starlark(k)}: {starlark(v)}" for k, v in value.items()) + "}"
    return json.dumps(value) if isinstance(value, str) else repr(value)


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
        """The target as this checker writes it in a BUILD file."""
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
        lines += [f"    {key} = {starlark(value)}," for key, value in self.extra.items()]
        return "\n".join(lines + [")"])


class Tree:
    """The first-party Python files of a checkout and the Bazel target each one needs."""

    def __init__(self, root: str):
        self.root = root
        self.errors: list[str] = []  # sources that do not parse

    def parse(self, path: str) -> ast.Module | None:
        """The syntax tree of `path` (relative), None (and an error noted) when it does not parse."""
        try:
            return parse(os.path.join(self.root, path))
        except (SyntaxError, UnicodeDecodeError) as e:
            self.errors.append(f"{path}: cannot parse ({e})")
            return None

    def rel(self, path):
        return os.path.relpath(path, self.root).replace(os.sep, "/")

    def files(self, top: str, pattern: str = "**/*.py") -> list[str]:
        """The files under `top` matching `pattern`, relative to the checkout and sorted."""
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
            if owned(name.replace(".", "/")) and (name in PACKAGES or "." in name):
                label = self.library_label(name)  # ff3d_tf.x, lab.x or tests.x.y (the checkout's root is on sys.path)
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
        for tool in [t for d in TOOL_DIRS for t in self.files(d, "*.py")]:
            stem = os.path.basename(tool)
            if any(t == stem or t.endswith("/" + stem) for t in texts):
                data.add(f"//{os.path.dirname(tool)}:{stem[:-3]}")
        return data

    def expected(self) -> list[Expected]:
        """The target of every first-party source that parses, libraries first, then tools, then tests."""
        return self._libraries() + self._tools() + self._tests()

    def _libraries(self) -> list[Expected]:
        """A py_library per module of LIBRARY_DIRS (the tools' folders left to `_tools`)."""
        out = []
        for path in [p for top in LIBRARY_DIRS for p in self.files(top) if os.path.dirname(p) not in TOOL_DIRS]:
            package, base = os.path.dirname(path), os.path.basename(path)
            is_package = base == "__init__.py"
            name = package.rsplit("/", 1)[-1] if is_package else base[:-3]
            module = package.replace("/", ".") + ("" if is_package else "." + name)
            tree = self.parse(path)
            if tree is not None:
                deps = self.first_party_deps(tree, module, is_package, f"//{package}:{name}")
                out.append(Expected(path, package, name, "py_library", deps))
        return out

    def _tools(self) -> list[Expected]:
        """A py_binary per tool of TOOL_DIRS, a py_library per helper `_*.py`."""
        out = []
        for path in [p for d in TOOL_DIRS for p in self.files(d, "*.py")]:
            package, name = os.path.dirname(path), os.path.basename(path)[:-3]
            tree = self.parse(path)
            if tree is None:
                continue
            label = f"//{package}:{name}"
            local_dirs = [package] + (["tools"] if package != "tools" else [])  # a lab tool's `_common` is tools/'s
            deps = self.first_party_deps(tree, name, False, label, local_dirs=local_dirs)
            data = self.data_needs(tree) - {label}
            rule = "py_library" if name.startswith("_") else "py_binary"
            out.append(Expected(path, package, name, rule, deps, data if rule == "py_binary" else ()))
        return out

    def _tests(self) -> list[Expected]:
        """A pytest_test per tests/**/test_*.py, a py_library per other module of tests/."""
        out = []
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
            else:  # a helper (conftest, fixtures): the data it names reaches every test that imports it
                out.append(Expected(path, package, name, "py_library", deps, self.data_needs(tree)))
        return out
