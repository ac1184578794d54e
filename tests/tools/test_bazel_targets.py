"""tools/check_bazel_targets.py: catches test files and modules without a Bazel target, wrong deps and slow splits."""
import importlib.util
import os
import subprocess
import sys
import textwrap

import pytest

# The checkout (realpath: under Bazel this file is a symlink in the runfiles tree, which holds only declared inputs).
CHECKOUT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.realpath(__file__))))
CHECKER = os.path.join(CHECKOUT, "tools", "check_bazel_targets.py")
PYTEST_LOAD = 'load("//bazel:pytest.bzl", "pytest_test")'
VISIBILITY = 'package(default_visibility = ["//visibility:public"])'

FAKE_TREE = {
    "ff3d_tf/__init__.py": '"""Package."""\n',
    "ff3d_tf/base.py": "VALUE = 1\n",
    "ff3d_tf/sub/__init__.py": "",
    "ff3d_tf/sub/uses.py": "from ff3d_tf import base\nfrom ff3d_tf.sub.helpers import twice\n",
    "ff3d_tf/sub/helpers.py": "def twice(x):\n    return 2 * x\n",
    "tools/_common.py": "import os\n",
    "tools/run.py": 'import _common\nfrom ff3d_tf.sub import uses\nDEFAULT = "configs/x.yaml"\n',
    "tests/conftest.py": "import pytest\n",
    "tests/test_base.py": textwrap.dedent("""\
        import pytest
        from ff3d_tf.base import VALUE

        def test_value():
            assert VALUE == 1

        @pytest.mark.slow
        def test_value_slowly():
            assert VALUE == 1
        """),
    "tests/sub/test_uses.py": textwrap.dedent("""\
        import subprocess
        from conftest import ROOT
        from ff3d_tf.sub import uses

        def test_tool():
            subprocess.run(["python", "tools/run.py"], check=True)
        """),
}

FAKE_BUILD = {
    "ff3d_tf/BUILD": """
        py_library(name = "ff3d_tf", srcs = ["__init__.py"])
        py_library(name = "base", srcs = ["base.py"])
        """,
    "ff3d_tf/sub/BUILD": """
        py_library(name = "sub", srcs = ["__init__.py"])
        py_library(name = "uses", srcs = ["uses.py"], deps = [":helpers", "//ff3d_tf:base"])
        py_library(name = "helpers", srcs = ["helpers.py"])
        """,
    "tools/BUILD": """
        py_library(name = "_common", srcs = ["_common.py"])
        py_binary(name = "run", srcs = ["run.py"], data = ["//configs"], deps = [":_common", "//ff3d_tf/sub:uses"])
        """,
    "configs/BUILD": 'filegroup(name = "configs", srcs = glob(["*.yaml"]))',
    "tests/BUILD": """
        load("//bazel:pytest.bzl", "pytest_test")
        py_library(name = "conftest", srcs = ["conftest.py"])
        pytest_test(name = "test_base", deps = ["//ff3d_tf:base"], slow = True)
        """,
    "tests/sub/BUILD": """
        load("//bazel:pytest.bzl", "pytest_test")
        pytest_test(name = "test_uses", data = ["//tools:run"], deps = ["//ff3d_tf/sub:uses"])
        """,
}


def _write(root, files):
    for rel, text in files.items():
        path = os.path.join(root, rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(textwrap.dedent(text).lstrip("\n"))


def _run_checker(root, *flags):
    return subprocess.run([sys.executable, CHECKER, "--root", str(root), *flags], capture_output=True, text=True,
                          timeout=120)


def _check(root, *flags):
    out = _run_checker(root, *flags)
    return out.returncode, out.stdout + out.stderr


def _fake_tree(tmp_path):
    _write(tmp_path, FAKE_TREE)
    _write(tmp_path, FAKE_BUILD)
    return tmp_path


def test_complete_tree_passes(tmp_path):
    rc, out = _check(_fake_tree(tmp_path))
    assert rc == 0, out
    assert "cover the tree (10 source files)" in out


def test_new_test_file_is_caught_and_its_stanza_fixes_it(tmp_path):
    root = _fake_tree(tmp_path)
    _write(root, {"tests/sub/test_new.py": """
        import pytest
        from ff3d_tf.sub import helpers

        @pytest.mark.parametrize("x", [1, pytest.param(2, marks=pytest.mark.slow)])
        def test_twice(x):
            assert helpers.twice(x) == 2 * x
        """})
    rc, out = _check(root)
    assert rc == 1
    assert "tests/sub/test_new.py: no pytest_test 'test_new' in tests/sub/BUILD" in out
    printed = _run_checker(root, "--print-missing")
    assert printed.returncode == 1
    stanza = printed.stdout[printed.stdout.index("# ---- add to tests/sub/BUILD"):]
    assert 'name = "test_new"' in stanza and 'deps = ["//ff3d_tf/sub:helpers"]' in stanza and "slow = True" in stanza
    assert "fast = False" not in stanza  # the unmarked case is a fast test
    with open(root / "tests/sub/BUILD", "a") as f:  # paste it as printed
        f.write("\n" + stanza.split("\n", 1)[1])
    assert _check(root) == (0, "Bazel targets cover the tree (11 source files)\n")


def test_new_module_is_caught_and_fix_writes_it(tmp_path):
    root = _fake_tree(tmp_path)
    _write(root, {"ff3d_tf/sub/more.py": "import numpy\nfrom ff3d_tf.sub.helpers import twice\n",
                  "ff3d_tf/newpkg/__init__.py": "from ff3d_tf import base\n",
                  "ff3d_tf/newpkg/wod.py": "from . import report\nfrom ff3d_tf.sub import uses\n",
                  "ff3d_tf/newpkg/report.py": "",
                  "tests/newpkg/test_wod.py": "from ff3d_tf.newpkg import wod\n\ndef test_x():\n    pass\n"})
    rc, out = _check(root)
    assert rc == 1
    assert "ff3d_tf/sub/more.py: no py_library 'more' in ff3d_tf/sub/BUILD" in out
    assert "ff3d_tf/newpkg/__init__.py: no ff3d_tf/newpkg/BUILD" in out
    assert "tests/newpkg/test_wod.py: no tests/newpkg/BUILD" in out
    rc, out = _check(root, "--fix")
    assert rc == 0, out
    with open(root / "ff3d_tf/newpkg/BUILD") as f:
        text = f.read()
    assert 'name = "newpkg",\n    srcs = ["__init__.py"],\n    deps = ["//ff3d_tf:base"],' in text
    assert 'name = "wod",\n    srcs = ["wod.py"],\n    deps = [\n        ":report",\n        "//ff3d_tf/sub:uses",\n    ],' in (
        text)
    with open(root / "tests/newpkg/BUILD") as f:
        assert f.read() == (PYTEST_LOAD + "\n\n" + VISIBILITY + "\n\n"
                            + 'pytest_test(\n    name = "test_wod",\n    deps = ["//ff3d_tf/newpkg:wod"],\n)\n')
    with open(root / "ff3d_tf/sub/BUILD") as f:
        assert 'name = "more",\n    srcs = ["more.py"],\n    deps = [":helpers"],' in f.read()


def test_checker_library_modules_are_targets_too(tmp_path):
    root = _fake_tree(tmp_path)
    _write(root, {"bazel/targets/__init__.py": "", "bazel/targets/lib.py": "from bazel.targets import util\n",
                  "bazel/targets/util.py": "", "tools/check.py": "from bazel.targets import lib\n"})
    rc, out = _check(root, "--fix")
    assert rc == 0, out
    with open(root / "bazel/targets/BUILD") as f:
        assert 'py_library(\n    name = "lib",\n    srcs = ["lib.py"],\n    deps = [":util"],\n)' in f.read()
    with open(root / "tools/BUILD") as f:
        assert 'name = "check",\n    srcs = ["check.py"],\n    deps = ["//bazel/targets:lib"],\n)' in f.read()


def test_lab_modules_and_tools_are_targets_too(tmp_path):
    """lab/ is a package of py_libraries beside ff3d_tf/; lab/tools/ holds py_binaries whose bare `import _common` is
    tools/_common.py; a test naming a lab tool gets it as data."""
    root = _fake_tree(tmp_path)
    _write(root, {"lab/__init__.py": "", "lab/bench.py": "from ff3d_tf import base\n",
                  "lab/study/__init__.py": "", "lab/study/steps.py": "from lab import bench\n",
                  "lab/tools/measure.py": 'import _common\nfrom lab.study import steps\nDEFAULT = "configs/x.yaml"\n',
                  "tests/lab/test_measure.py": 'def test_x():\n    assert "lab/tools/measure.py"\n'})
    rc, out = _check(root)
    assert rc == 1 and "lab/tools/measure.py: no lab/tools/BUILD (a py_binary 'measure' is needed)" in out, out
    rc, out = _check(root, "--fix")
    assert rc == 0, out
    with open(root / "lab/study/BUILD") as f:
        assert 'py_library(\n    name = "steps",\n    srcs = ["steps.py"],\n    deps = ["//lab:bench"],\n)' in f.read()
    with open(root / "lab/tools/BUILD") as f:
        assert ('py_binary(\n    name = "measure",\n    srcs = ["measure.py"],\n    data = ["//configs"],\n    deps = [\n'
                '        "//lab/study:steps",\n        "//tools:_common",\n    ],\n)') in f.read()
    with open(root / "tests/lab/BUILD") as f:
        assert 'pytest_test(\n    name = "test_measure",\n    data = ["//lab/tools:measure"],\n)' in f.read()


def test_build_file_shapes_it_writes_and_reads(tmp_path):
    root = _fake_tree(tmp_path)
    _write(root, {"BUILD": 'package(default_visibility = ["//visibility:public"])\nexports_files(["pytest.ini"])\n',
                  "tests/BUILD": FAKE_BUILD["tests/BUILD"].replace('"pytest_test")', '"pytest_test", alias = "x")')
                  + 'pytest_test(name = "test_more", env = {"A": "1"}, shard_count = -2, flaky = True, tags = [],'
                    ' size = None, timeout = "short")\n',
                  "tests/test_more.py": "def test_x():\n    pass\n"})
    rc, out = _check(root, "--fix")
    assert rc == 0, out
    with open(root / "tests/BUILD") as f:
        assert ('pytest_test(\n    name = "test_more",\n    env = {"A": "1"},\n    shard_count = -2,\n'
                '    flaky = True,\n    tags = [],\n    size = None,\n    timeout = "short",\n)') in f.read()
    assert _check(root) == (0, "Bazel targets cover the tree (11 source files)\n")


REFUSED = {  # a line that the reader refuses in a BUILD file: what the message says of it
    "import os": ["`import os` (Import) is not a call of a rule"],
    '__import__("os").system("touch {marker}")': ["`__import__('os').system` (Attribute) is called;"],
    '_private(name = "x")': ["`_private(name='x')` (Call) calls a private name"],
    'py_library(name = "x", srcs = [open("{marker}", "w").name])': ["`open(", "(Attribute) is not a literal"],
    'py_library(name = "x", deps = [str(1)])': ["`str(1)` (Call) is not a literal"],
    "SRCS = ['base.py']": ["`SRCS = ['base.py']` (Assign) is not a call"],
    'py_library(name = "x", srcs = SRCS)': ["`SRCS` (Name) is not a literal"],
    'py_library(**{{"name": "x"}})': ["`{{'name': 'x'}}` (Dict) is spread into py_library() with **"],
    'py_library("x")': ["`'x'` (Constant) is a positional argument of py_library()"],
    'py_library(name = "x", srcs = glob(["../../**"]))': ["has the pattern '../../**', which leaves the package"],
    'py_library(name = "x", srcs = ["a.py"] + ["b.py"])': ["(BinOp) is not a literal"],
    'py_library(name = "x", deps = ":base")': ["`':base'` (Constant) is given to deps, which takes a list of strings"],
    "def f(): pass": ["`def f(): pass` (FunctionDef) is not a call"],
    'py_library(name = "x", srcs = [f"{{x}}"])': ["(JoinedStr) is not a literal"],
    'py_library(name = "x", srcs = ["a.py"]': ["cannot parse ('(' was never closed)"],
    'py_library(name = "base")': ["target 'base' defined twice"],
}


@pytest.mark.parametrize("line", sorted(REFUSED))
def test_build_file_with_code_is_refused_and_nothing_of_it_runs(tmp_path, line):
    root = _fake_tree(tmp_path)
    marker = tmp_path / "ran"
    written = ('py_library(name = "ff3d_tf", srcs = ["__init__.py"])\npy_library(name = "base", srcs = ["base.py"])\n'
               + line.format(marker=marker) + "\n")
    _write(root, {"ff3d_tf/BUILD": written})
    rc, out = _check(root, "--fix")  # checks, fixes, then checks again
    assert rc == 1
    message = next(m for m in out.splitlines() if m.startswith("  ff3d_tf/BUILD:3: "))  # file and line
    assert all(part.format(marker=marker) in message for part in REFUSED[line]), message
    assert "no py_library" not in out, out  # the targets of a file it cannot read are not reported one by one
    assert "not fixed: ff3d_tf/BUILD not rewritten: it cannot be read" in out
    with open(root / "ff3d_tf/BUILD") as f:
        assert f.read() == written  # --fix leaves it alone
    assert not marker.exists()


def test_wrong_deps_data_and_slow_split_are_named(tmp_path):
    root = _fake_tree(tmp_path)
    build = dict(FAKE_BUILD)
    build["ff3d_tf/sub/BUILD"] = build["ff3d_tf/sub/BUILD"].replace('":helpers", ', "")  # import without a dep
    build["tools/BUILD"] = build["tools/BUILD"].replace(', "//ff3d_tf/sub:uses"', ', "//ff3d_tf:base"')
    build["tests/BUILD"] = build["tests/BUILD"].replace(", slow = True", "")  # the file has a slow test
    build["tests/sub/BUILD"] = build["tests/sub/BUILD"].replace('data = ["//tools:run"], ', "")
    _write(root, build)
    rc, out = _check(root)
    assert rc == 1
    assert "ff3d_tf/sub/BUILD target 'uses' deps lack //ff3d_tf/sub:helpers" in out
    assert "target 'run' deps lack //ff3d_tf/sub:uses" in out
    assert "target 'run' deps name modules it does not import: //ff3d_tf:base" in out
    assert "target 'test_base' has fast = True, slow = False; the file needs fast = True, slow = True" in out
    assert "target 'test_uses' data lack //tools:run" in out
    assert out.count("\n  ") == 5, out  # nothing else
    # --fix rewrites the targets, keeping attributes it does not derive and data it cannot see.
    with open(root / "tests/BUILD", "a") as f:
        f.write('pytest_test(name = "test_more", timeout = "eternal", data = ["//configs"], fast = False, slow = True)\n')
    _write(root, {"tests/test_more.py": "def test_x():\n    pass\n"})
    rc, out = _check(root, "--fix")
    assert rc == 0, out
    with open(root / "tests/BUILD") as f:
        text = f.read()
    assert 'pytest_test(\n    name = "test_more",\n    data = ["//configs"],\n    timeout = "eternal",\n)' in text
    assert 'name = "test_base",\n    deps = ["//ff3d_tf:base"],\n    slow = True,\n)' in text


def test_only_slow_file_and_removed_source(tmp_path):
    root = _fake_tree(tmp_path)
    _write(root, {"tests/test_base.py": "import pytest\nfrom ff3d_tf.base import VALUE\n"
                                        "pytestmark = pytest.mark.slow\n\ndef test_value():\n    assert VALUE\n"})
    os.remove(root / "ff3d_tf/sub/helpers.py")
    with open(root / "ff3d_tf/sub/uses.py", "w") as f:
        f.write("from ff3d_tf import base\n")
    _write(root, {"tools/half_written.py": "def main(:\n"})
    rc, out = _check(root)
    assert rc == 1
    assert "the file needs fast = False, slow = True" in out
    assert "ff3d_tf/sub/BUILD target 'helpers': source ff3d_tf/sub/helpers.py does not exist" in out
    assert "ff3d_tf/sub/BUILD target 'uses' deps name modules it does not import: //ff3d_tf/sub:helpers" in out
    assert "tools/half_written.py: cannot parse (invalid syntax" in out


def test_dependency_cycle_is_named(tmp_path):
    # helpers imports uses inside a function (a lazy import is still a dep): uses -> helpers -> uses.
    root = _fake_tree(tmp_path)
    _write(root, {"ff3d_tf/sub/helpers.py": "def twice(x):\n    from ff3d_tf.sub import uses\n    return 2 * x\n"})
    rc, out = _check(root, "--fix")
    assert rc == 1
    assert "cycle in the deps: //ff3d_tf/sub:helpers -> //ff3d_tf/sub:uses -> //ff3d_tf/sub:helpers" in out, out


def test_this_checkout_is_covered():
    rc, out = _check(CHECKOUT)
    assert rc == 0, out


def test_pytest_runner_maps_bazel_test_environment():
    spec = importlib.util.spec_from_file_location("pytest_runner", os.path.join(CHECKOUT, "bazel", "pytest_runner.py"))
    runner = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(runner)
    env = {"TEST_TMPDIR": "/t", "XML_OUTPUT_FILE": "/x/test.xml", "TESTBRIDGE_TEST_ONLY": "bucketed"}
    assert runner.pytest_args(["-m", "not slow", "tests/test_a.py"], env) == [
        "-q", "-p", "no:cacheprovider", "-m", "not slow", "tests/test_a.py", "--basetemp", "/t/pytest",
        "--junitxml", "/x/test.xml", "-k", "bucketed"]
    assert runner.pytest_args(["tests/test_a.py"], {}) == ["-q", "-p", "no:cacheprovider", "tests/test_a.py"]
