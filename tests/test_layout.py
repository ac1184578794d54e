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
    with open(os.path.join(log, "NOTICE.md"), encoding="utf-8") as f:
        notice = f.read()
    # a licence notice: the licence, the attribution, the source commit and what the files are used for
    for needed in ("CC BY-NC-SA 4.0", "Argo AI", "b7321d1f71f6ce0ecdd151f4f2b648338c191edd", "Use here"):
        assert needed in notice, needed
    assert len(os.listdir(os.path.join(log, "sensors", "lidar"))) == 2


# --- Floors: foundations at the bottom, three sibling pipelines above them, tools on top; the lab beside them ---------
# A module of ff3d_tf imports only modules of its own floor or lower; the pipelines never import one another (each
# stands on the foundations alone); nothing in ff3d_tf imports a tool, and no tool imports another tool (`_common`,
# the tools' shared flag parsing, is not a tool). The lab (lab/: studies, benchmarks, profilers and their tools in
# lab/tools/) may import any of ff3d_tf and `_common`, but neither ff3d_tf nor a tool of tools/ imports the lab: the
# installed package never needs it. Every import counts, function-local ones included.
FOUNDATION_RANKS = {  # within the foundation floor: a module imports ranks <= its own
    "schema": 0, "cpu": 0, "internals": 0, "parallel": 0, "json_io": 0, "geometry": 0, "xla_program": 0, "stages": 0,
    "predictor": 0,
    "config": 1,
    "data": 2, "model": 2, "metrics": 2, "metrics_av2": 2, "viz": 2, "viz3d": 2, "xla_export_dir": 2,
    "checkpoints": 3,
}
PIPELINES = ("labels", "training", "inference", "fuzz")
# Rooms of ff3d_tf/data: one per source. A room never imports another; the synthetic generators may import the formats
# they write. The shared modules at ff3d_tf/data/ (pairs, pair records, the job shape) may import any room.
DATA_ROOMS = ("wod", "av2", "files", "synthetic")
ROOMS_THAT_MAY_IMPORT_ROOMS = ("synthetic",)
TOOL_HELPERS = ("_common",)


def _imports(path: str, package: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in the file, at any depth; `package` resolves relative ones."""
    import ast
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            found += [(node.lineno, f"{base}.{a.name}" if base else a.name) for a in node.names]
    return found


def _floor(module: str) -> tuple[str, str] | None:
    """("foundation" | "pipeline" | "tool" | "lab" | "lab tool", the top-level part) of a first-party module name,
    None otherwise."""
    parts = module.split(".")
    if parts[0] == "tools" and len(parts) > 1:
        return "tool", parts[1]
    if parts[:2] == ["lab", "tools"] and len(parts) > 2:
        return "lab tool", parts[2]
    if parts[0] == "lab":
        return "lab", parts[1] if len(parts) > 1 else ""
    if parts[0] != "ff3d_tf":
        return None
    if len(parts) == 1:
        return "foundation", ""
    return ("pipeline", parts[1]) if parts[1] in PIPELINES else ("foundation", parts[1])


def _module_names(folder: str) -> set[str]:
    return {n[:-3] for n in os.listdir(folder) if n.endswith(".py")} if os.path.isdir(folder) else set()


def layering_violations(root: str) -> list[str]:
    """Every import under `root`/ff3d_tf, `root`/tools and `root`/lab that breaks the floors, as "file:line: a -> b
    (why)".

    Tools run with tools/ on sys.path, so a bare `import train` in a tool is the tool tools.train; a lab tool runs with
    its own folder and tools/ on sys.path (a bare `import run_xla` there is lab.tools.run_xla, `import _common` is
    tools._common).
    """
    tool_names = _module_names(os.path.join(root, "tools"))
    lab_tool_names = _module_names(os.path.join(root, "lab", "tools"))
    out = []
    for top in ("ff3d_tf", "tools", "lab"):
        for dirpath, _, names in os.walk(os.path.join(root, top)):
            for name in sorted(n for n in names if n.endswith(".py")):
                path = os.path.join(dirpath, name)
                rel = os.path.relpath(path, root)
                module = rel[:-3].replace(os.sep, ".").removesuffix(".__init__")
                package = module if name == "__init__.py" else module.rpartition(".")[0]
                in_lab_tools = package == "lab.tools"
                for line, target in _imports(path, package):
                    first = target.split(".")[0]
                    if in_lab_tools and first in lab_tool_names:
                        target = f"lab.tools.{target}"
                    elif (top == "tools" or in_lab_tools) and first in tool_names:
                        target = f"tools.{target}"
                    if why := _why_not(module, target):
                        out.append(f"{rel}:{line}: {why}")
    return sorted(set(out))


def _data_room(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if len(parts) > 3 and parts[:2] == ["ff3d_tf", "data"] and parts[2] in DATA_ROOMS else None


def _why_not(module: str, target: str) -> str | None:
    room, target_room = _data_room(module), _data_room(target)
    if room and target_room and room != target_room and room not in ROOMS_THAT_MAY_IMPORT_ROOMS:
        return f"{module} -> {target} (dataset rooms are siblings: none imports another)"
    here, there = _floor(module), _floor(target)
    if there is None or here is None or here == there:
        return None
    (floor, part), (target_floor, target_part) = here, there
    arrow = f"{module} -> {target}"
    lab = ("lab", "lab tool")
    if target_floor == "lab tool":
        return f"{arrow} (imports a tool)"
    if target_floor == "lab":
        return None if floor in lab else f"{arrow} ({'a tool' if floor == 'tool' else 'the product'} imports the lab)"
    if target_floor == "tool":
        return None if floor in ("tool",) + lab and target_part in TOOL_HELPERS else f"{arrow} (imports a tool)"
    if floor in ("tool",) + lab:
        return None
    if floor == "pipeline":
        return f"{arrow} (pipelines are siblings: none imports another)" if target_floor == "pipeline" else None
    if target_floor == "pipeline":
        return f"{arrow} (a foundation imports a pipeline)"
    if part and target_part and FOUNDATION_RANKS.get(target_part, 99) > FOUNDATION_RANKS.get(part, -1):
        return f"{arrow} (foundation rank {FOUNDATION_RANKS.get(part)} imports rank {FOUNDATION_RANKS.get(target_part)})"
    return None


def test_every_module_has_a_floor():
    parts = {n[:-3] if n.endswith(".py") else n for n in os.listdir(os.path.join(ROOT, "ff3d_tf"))
             if n.endswith(".py") or os.path.isdir(os.path.join(ROOT, "ff3d_tf", n))} - {"__init__", "__pycache__"}
    assert parts - set(PIPELINES) - set(FOUNDATION_RANKS) == set(), "give each new module a floor here"
    gone = (set(PIPELINES) | set(FOUNDATION_RANKS)) - parts
    assert gone == set(), f"floors of modules that are gone (remove them here): {gone}"


def test_the_floors_hold():
    assert layering_violations(ROOT) == []


def _fake_tree(root, files: dict[str, str]) -> str:
    for rel, text in files.items():
        path = os.path.join(root, rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)
    return str(root)


def test_the_layering_check_finds_each_kind_of_arrow(tmp_path):
    root = _fake_tree(tmp_path, {
        "ff3d_tf/__init__.py": "",
        "ff3d_tf/schema.py": "",
        "ff3d_tf/config.py": "from ff3d_tf import schema\n",  # rank 1 -> 0: fine
        "ff3d_tf/geometry.py": "def f():\n    from ff3d_tf import config\n",  # rank 0 -> 1, function-local
        "ff3d_tf/model/__init__.py": "from . import layers\nfrom ..training import trainer\n",  # relative: -> pipeline
        "ff3d_tf/model/layers.py": "",
        "ff3d_tf/training/trainer.py": "from ff3d_tf.model import layers\nimport ff3d_tf.inference.predictor\n",
        "ff3d_tf/inference/predictor.py": "from ff3d_tf.checkpoints import x\n",  # pipeline -> foundation: fine
        "ff3d_tf/labels/box_flow.py": "def g():\n    from ff3d_tf.training.trainer import Trainer\n",
        "tools/_common.py": "",
        "tools/a.py": "import _common\nfrom ff3d_tf.training import trainer\n",  # fine
        "tools/b.py": "from tools import a\n",
        "tools/c.py": "def h():\n    from a import helper\n",  # tools/ is on sys.path: `a` is tools/a.py
        "ff3d_tf/data/__init__.py": "",
        "ff3d_tf/data/pairs.py": "from ff3d_tf.data.wod import waymo\n",  # shared -> a room: fine
        "ff3d_tf/data/wod/waymo.py": "from ff3d_tf.data import pairs\n",  # a room -> shared: fine
        "ff3d_tf/data/av2/argoverse2.py": "from ff3d_tf.data.wod.waymo import x\n",
        "ff3d_tf/data/synthetic/av2.py": "from ff3d_tf.data.av2 import argoverse2\n",  # writes that format: fine
        "ff3d_tf/stages.py": "import json\n\n\ndef f():\n    from lab import bench\n",  # the product -> the lab
        "tools/d.py": "import lab.bench\n",  # a tool -> the lab
        "lab/__init__.py": "",
        "lab/bench.py": "from ff3d_tf.schema import x\n",  # the lab -> the product: fine
        "lab/training/study.py": "from lab import bench\nfrom ff3d_tf.training import trainer\nfrom tools import a\n",
        "lab/tools/t.py": "import _common\nfrom lab.training import study\n",  # _common is tools/_common.py: fine
        "lab/tools/u.py": "import t\n",  # lab/tools/ is on sys.path: `t` is lab/tools/t.py
    })
    found = layering_violations(root)
    assert found == sorted([
        "ff3d_tf/geometry.py:2: ff3d_tf.geometry -> ff3d_tf.config (foundation rank 0 imports rank 1)",
        "ff3d_tf/labels/box_flow.py:2: ff3d_tf.labels.box_flow -> ff3d_tf.training.trainer.Trainer (pipelines are "
        "siblings: none imports another)",
        "ff3d_tf/model/__init__.py:2: ff3d_tf.model -> ff3d_tf.training.trainer (a foundation imports a pipeline)",
        "ff3d_tf/training/trainer.py:2: ff3d_tf.training.trainer -> ff3d_tf.inference.predictor (pipelines are "
        "siblings: none imports another)",
        "tools/b.py:1: tools.b -> tools.a (imports a tool)",
        "tools/c.py:2: tools.c -> tools.a.helper (imports a tool)",
        "ff3d_tf/data/av2/argoverse2.py:1: ff3d_tf.data.av2.argoverse2 -> ff3d_tf.data.wod.waymo.x (dataset rooms are "
        "siblings: none imports another)",
        "ff3d_tf/stages.py:5: ff3d_tf.stages -> lab.bench (the product imports the lab)",
        "tools/d.py:1: tools.d -> lab.bench (a tool imports the lab)",
        "lab/training/study.py:3: lab.training.study -> tools.a (imports a tool)",
        "lab/tools/u.py:1: lab.tools.u -> lab.tools.t (imports a tool)",
    ]), found


# --- The model holds no state of its own: what it computes is its config and its execution plan --------------------
# A module of ff3d_tf/model/ binds at its top level only constants (UPPER_CASE), private names (a logger, helpers),
# functions and classes, and has no `global` statement: no module variable that a study, a test or a tool could
# assign to change the arithmetic of every model in the process (`ff3d_tf.model.plan` is how).


def module_state(path: str) -> list[str]:
    """"line: name" of each top-level binding of a lowercase public name, and each `global` statement, in `path`."""
    import ast
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    found = []
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, (ast.AnnAssign, ast.AugAssign)) else [])
        for target in targets:
            for name in ast.walk(target):
                if isinstance(name, ast.Name) and not (name.id.isupper() or name.id.startswith("_")):
                    found.append(f"{node.lineno}: {name.id}")
    found += [f"{n.lineno}: global {', '.join(n.names)}" for n in ast.walk(tree) if isinstance(n, ast.Global)]
    return found


def test_module_state_is_found(tmp_path):
    path = tmp_path / "m.py"
    path.write_text("FORMS = ('a',)\n_LOG = None\nforms = 'fast'\n\ndef f():\n    global _x\n")
    assert module_state(str(path)) == ["3: forms", "6: global _x"]


def test_the_model_holds_no_module_state():
    folder = os.path.join(ROOT, "ff3d_tf", "model")
    found = {name: module_state(os.path.join(folder, name)) for name in sorted(os.listdir(folder))
             if name.endswith(".py")}
    assert {name: state for name, state in found.items() if state} == {}
