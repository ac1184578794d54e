"""Every tool's start-up is one explicit call, `_common.start(job)`, the first statement of its `main()`, and nothing
at import: importing a tool imports no TensorFlow (so that the call's environment reaches TensorFlow when `main`
imports it), and `start` refuses to run after TensorFlow was imported."""
import ast
import glob
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.realpath(__file__))))
NOT_TOOLS = ("_common.py", "check_bazel_targets.py")  # the shared helper; the Bazel check runs no model
TOOLS = sorted(p for folder in ("tools", "lab/tools") for p in glob.glob(os.path.join(ROOT, folder, "*.py"))
               if os.path.basename(p) not in NOT_TOOLS)


def _start_job(path: str) -> str | None:
    """The job named by `_common.start(...)` as the first statement of `main()` (after its docstring), else None."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    main = next((n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main"), None)
    if main is None:
        return None
    body = main.body[1:] if isinstance(main.body[0], ast.Expr) and isinstance(main.body[0].value, ast.Constant) \
        else main.body
    call = body[0].value if isinstance(body[0], ast.Expr) else None
    if (isinstance(call, ast.Call) and ast.unparse(call.func) == "_common.start" and len(call.args) == 1
            and isinstance(call.args[0], ast.Constant)):
        return call.args[0].value
    return None


def test_every_tool_names_its_job_first_in_main():
    sys.path.insert(0, os.path.join(ROOT, "tools"))
    import _common
    assert len(TOOLS) > 30
    jobs = {os.path.relpath(p, ROOT): _start_job(p) for p in TOOLS}
    assert {t: j for t, j in jobs.items() if j not in _common.JOBS} == {}, "main() must begin with _common.start(job)"
    assert jobs["tools/train.py"] == "train" and jobs["tools/predict.py"] == "inference"


IMPORT_ALL = """
import importlib.util, json, sys
imported = {}
for path in sys.argv[1:]:
    spec = importlib.util.spec_from_file_location("tool_" + str(len(imported)), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    imported[path] = "tensorflow" in sys.modules
    if imported[path]:
        break
print(json.dumps(imported))
"""


def test_importing_a_tool_imports_no_tensorflow():
    """Each tool imported in turn in one fresh process (the tools' folder on sys.path, as when run): TensorFlow is
    still not imported after the last one."""
    import json
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.join(ROOT, "tools"), ROOT])}
    out = subprocess.run([sys.executable, "-c", IMPORT_ALL, *TOOLS], capture_output=True, text=True, env=env,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    imported = json.loads(out.stdout.strip().splitlines()[-1])
    assert [os.path.relpath(p, ROOT) for p, tf in imported.items() if tf] == [], "imports TensorFlow at import"
    assert len(imported) == len(TOOLS)


START_AFTER_TENSORFLOW = """
import sys
sys.path.insert(0, sys.argv[1])
import _common
added = _common.start("train")
import os
print(sorted(added), os.environ["TF_CPP_MIN_LOG_LEVEL"])
import tensorflow
try:
    _common.start("inference")
except _common.StartupError as e:
    print("refused:", e)
"""


def test_start_applies_the_job_and_refuses_after_tensorflow():
    from ff3d_tf import cpu
    # the start-up keys and the log level left out, so that the values shown are start()'s own defaults
    env = {k: v for k, v in os.environ.items() if k not in (*cpu.STARTUP_KEYS, "TF_CPP_MIN_LOG_LEVEL")}
    out = subprocess.run([sys.executable, "-c", START_AFTER_TENSORFLOW, os.path.join(ROOT, "tools")],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    first, refused = out.stdout.strip().splitlines()[-2:]
    assert first == f"{sorted(cpu.startup_environment('train', environ=env))} 2"
    assert refused.startswith("refused: start('inference') after TensorFlow was imported")


def test_an_unknown_job_is_refused():
    sys.path.insert(0, os.path.join(ROOT, "tools"))
    import _common
    with pytest.raises(ValueError, match="train, inference"):
        _common.start("serve")
