"""Reading BUILD files as data: each is parsed with `ast` and checked against the shapes below; nothing in it runs.

A BUILD file read here holds only top-level calls (comments aside), each of one of these shapes:

    load("<label>", "<symbol>", ..., <alias> = "<symbol>")
    package(<key> = <literal>, ...)
    exports_files(<literal>, ..., <key> = <literal>, ...)
    <rule>(name = "<name>", <key> = <value>, ...)     # any rule or macro; keyword arguments only

A literal is a string, an int, True, False, None, a list of literals or a dict with string keys; it is read with
`ast.literal_eval` once its shape is checked. A rule attribute is a literal or `glob([<pattern>, ...], exclude = [...])`
with patterns inside the package (no `..`, no leading `/`); srcs, deps and data are lists of strings. Anything else
(an assignment, an import, a def, a name, a call inside a value, `**kwargs`, a private `_rule`, ...) is a
BuildFileError whose message starts with `<file>:<line>:` and names the construct.
"""
from __future__ import annotations

import ast
import glob as globlib
import os

DIRECTIVES = ("load", "package", "exports_files")
LABEL_LISTS = ("srcs", "deps", "data")  # attributes that must be lists of strings
GLOB_KEYWORDS = {"include": list, "exclude": list, "exclude_directories": int, "allow_empty": bool}
SHOWN_CHARS = 60  # of a refused construct, in the message


class BuildFileError(ValueError):
    """A BUILD file this reader cannot parse or refuses; the message starts with `<file>:<line>:`."""


def _shown(node: ast.AST) -> str:
    """`node` as source, on one line and cut to SHOWN_CHARS (strings come out escaped, as Python reprs)."""
    text = " ".join(ast.unparse(node).split())
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + "..."


def _refuse(where: str, node: ast.AST, what: str) -> BuildFileError:
    """The error `<file>:<line>: `<node>` (<node type>) <what>`."""
    return BuildFileError(f"{where}:{node.lineno}: `{_shown(node)}` ({type(node).__name__}) {what}")


def _check_literal(node: ast.AST, where: str) -> None:
    """Raise unless `node` is a literal: str, int, bool, None, a list of literals or a dict with string keys."""
    if isinstance(node, ast.Constant) and (node.value is None or type(node.value) in (str, int, bool)):
        return
    if (isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub) and isinstance(node.operand, ast.Constant)
            and type(node.operand.value) is int):
        return
    if isinstance(node, ast.List):
        for item in node.elts:
            _check_literal(item, where)
        return
    if isinstance(node, ast.Dict):
        for key, value in zip(node.keys, node.values):
            if not (isinstance(key, ast.Constant) and type(key.value) is str):
                raise _refuse(where, key or value, "is not a string key of a dict")
            _check_literal(value, where)
        return
    raise _refuse(where, node, "is not a literal (a string, int, bool, None, list or dict)")


def literal(node: ast.AST, where: str):
    """The value of the literal `node` (see _check_literal); `where` names the file in the error."""
    _check_literal(node, where)
    return ast.literal_eval(node)


def _glob(call: ast.Call, where: str, package_dir: str) -> list[str]:
    """The files of `package_dir` (relative, sorted) that a `glob(...)` attribute value names."""
    if len(call.args) > 1 or any(k.arg not in GLOB_KEYWORDS for k in call.keywords):
        raise _refuse(where, call, "is not glob([patterns], exclude = [patterns])")
    args = {"include": literal(call.args[0], where)} if call.args else {}
    args.update((k.arg, literal(k.value, where)) for k in call.keywords)
    for key, value in args.items():
        kind = GLOB_KEYWORDS[key]
        if not isinstance(value, kind) or (kind is list and not all(isinstance(p, str) for p in value)):
            kind_name = "list of strings" if kind is list else kind.__name__
            raise _refuse(where, call, f"has a {key} argument that is not a {kind_name}")
    for pattern in args.get("include", []) + args.get("exclude", []):
        if pattern.startswith("/") or ".." in pattern.split("/"):
            raise _refuse(where, call, f"has the pattern {pattern!r}, which leaves the package")
    found = set()
    for pattern in args.get("include", []):
        found.update(os.path.relpath(p, package_dir)
                     for p in globlib.glob(os.path.join(package_dir, pattern), recursive=True) if os.path.isfile(p))
    for pattern in args.get("exclude", []):
        found.difference_update(os.path.relpath(p, package_dir)
                                for p in globlib.glob(os.path.join(package_dir, pattern), recursive=True))
    return sorted(found)


def _directive(call: ast.Call, where: str) -> None:
    """Check the arguments of a load(), package() or exports_files() call; what they say is not needed here."""
    name = call.func.id
    spread = next((k.value for k in call.keywords if k.arg is None), None)
    if spread is not None:
        raise _refuse(where, spread, f"is spread into {name}() with **; write each argument out")
    if name == "load":
        if len(call.args) < 2 or not all(isinstance(a, ast.Constant) and type(a.value) is str
                                         for a in call.args + [k.value for k in call.keywords]):
            raise _refuse(where, call, 'is not load("<label>", "<symbol>", ..., <alias> = "<symbol>")')
    elif name == "package" and call.args:
        raise _refuse(where, call, "takes keyword arguments only")
    for node in call.args + [k.value for k in call.keywords]:
        literal(node, where)


def _rule(call: ast.Call, where: str, package_dir: str) -> dict:
    """{"rule": <rule>, <attribute>: <value>, ...} of a rule call, in the order written."""
    rule = call.func.id
    if rule.startswith("_"):
        raise _refuse(where, call, "calls a private name; a BUILD file can call only rules and loaded macros")
    if call.args:
        raise _refuse(where, call.args[0], f"is a positional argument of {rule}(); rules take keyword arguments only")
    attrs = {"rule": rule}
    for keyword in call.keywords:
        if keyword.arg is None:
            raise _refuse(where, keyword.value, f"is spread into {rule}() with **; write each attribute out")
        if keyword.arg == "rule":
            raise _refuse(where, keyword.value, "is given to `rule`, an attribute name this reader keeps for the rule")
        value = keyword.value
        is_glob = isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id == "glob"
        attrs[keyword.arg] = _glob(value, where, package_dir) if is_glob else literal(value, where)
        if keyword.arg in LABEL_LISTS and not (isinstance(attrs[keyword.arg], list)
                                               and all(isinstance(v, str) for v in attrs[keyword.arg])):
            raise _refuse(where, value, f"is given to {keyword.arg}, which takes a list of strings")
    if not isinstance(attrs.get("name"), str) or not attrs["name"]:
        raise _refuse(where, call, "has no name (a non-empty string)")
    return attrs


def _parse(path: str, where: str) -> ast.Module:
    """The syntax tree of the BUILD file `path`; BuildFileError when it is not UTF-8 or not Python syntax."""
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except UnicodeDecodeError as e:
        raise BuildFileError(f"{where}:1: not UTF-8 ({e.reason})") from None
    try:
        return ast.parse(text, filename=where)
    except SyntaxError as e:
        raise BuildFileError(f"{where}:{e.lineno or 1}: cannot parse ({e.msg})") from None
    except (ValueError, RecursionError, MemoryError) as e:  # NUL bytes, nesting too deep for the parser
        raise BuildFileError(f"{where}:1: cannot parse ({type(e).__name__}: {e})") from None


def read_build_file(path: str, package_dir: str, where: str | None = None) -> dict[str, dict]:
    """Targets of one BUILD file: {name: {"rule": ..., "name": ..., "srcs": [...], ...}} (attributes as written).

    `package_dir` is the folder that glob() patterns are relative to; `where` names the file in errors (default
    `path`). Raises BuildFileError for anything outside the shapes of this module's docstring.
    """
    where = where or path
    targets: dict[str, dict] = {}
    for stmt in _parse(path, where).body:
        call = stmt.value if isinstance(stmt, ast.Expr) else stmt
        if not isinstance(call, ast.Call):
            raise _refuse(where, call, "is not a call of a rule, load(), package() or exports_files()")
        if not isinstance(call.func, ast.Name):
            raise _refuse(where, call.func, "is called; a BUILD file calls only rules, load(), package() and "
                                            "exports_files()")
        if call.func.id in DIRECTIVES:
            _directive(call, where)
            continue
        attrs = _rule(call, where, package_dir)
        if attrs["name"] in targets:
            raise BuildFileError(f"{where}:{call.lineno}: target {attrs['name']!r} defined twice")
        targets[attrs["name"]] = attrs
    return targets


def bazel_ignored(root: str) -> list[str]:
    """The folders that `root`/.bazelignore lists (relative, without slashes at the ends)."""
    path = os.path.join(root, ".bazelignore")
    if not os.path.exists(path):
        return []
    with open(path, encoding="utf-8") as f:
        return [line.strip().strip("/") for line in f if line.strip() and not line.startswith("#")]


class Workspace:
    """The BUILD files of a checkout outside its .bazelignore'd folders.

    packages: {package: targets}, "" for the root; errors: what made a file unreadable; unreadable: those packages
    (in `packages` with no targets).
    """

    def __init__(self, root: str):
        self.packages: dict[str, dict[str, dict]] = {}
        self.errors: list[str] = []
        self.unreadable: set[str] = set()
        ignored = set(bazel_ignored(root))
        for dirpath, dirnames, filenames in os.walk(root):
            rel = os.path.relpath(dirpath, root).replace(os.sep, "/")
            rel = "" if rel == "." else rel
            dirnames[:] = sorted(d for d in dirnames
                                 if not d.startswith((".", "bazel-")) and f"{rel}/{d}".strip("/") not in ignored)
            name = next((n for n in ("BUILD", "BUILD.bazel") if n in filenames), None)
            if name is None:
                continue
            try:
                self.packages[rel] = read_build_file(os.path.join(dirpath, name), dirpath, f"{rel}/{name}".lstrip("/"))
            except BuildFileError as e:
                self.errors.append(str(e))
                self.unreadable.add(rel)
                self.packages[rel] = {}


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
