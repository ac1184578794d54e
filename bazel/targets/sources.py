"""What a Python source needs, read from its syntax tree: the modules it imports, the strings it holds (file names
it uses) and, for a pytest file, whether it has tests not marked / marked `@pytest.mark.slow`."""
from __future__ import annotations

import ast


def parse(path: str) -> ast.Module:
    """The syntax tree of the file `path` (SyntaxError, UnicodeDecodeError as they come)."""
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
