"""pytest_test: the Bazel targets of one pytest file, split by the `slow` marker as `make test` / `make test-slow` are.

    pytest_test(
        name = "test_pairs",            # the file is test_pairs.py
        deps = ["//ff3d_tf/data:pairs"],
        fast = True,                    # the file has tests not marked slow: target `test_pairs`
        slow = True,                    # the file has tests marked @pytest.mark.slow: target `test_pairs_slow`
    )

The `_slow` target carries the tag `slow`, which .bazelrc filters out of `bazel test //...`; run them with
`bazel test --test_tag_filters=slow //...`. Every target gets pytest.ini and tests/conftest.py (with its deps) so that
pytest sees the same configuration and fixtures as in the checkout. tools/check_bazel_targets.py keeps these stanzas
in step with the files.
"""

_RUNNER = "//bazel:pytest_runner.py"

def pytest_test(name, deps = [], data = [], fast = True, slow = False, timeout = "long", tags = [], **kwargs):
    """One py_test running the fast tests of `<name>.py` and, when `slow`, one running its slow tests."""
    if not fast and not slow:
        fail("pytest_test %s: at least one of fast, slow must be True" % name)
    src = name + ".py"

    # timeout "long" (900 s): the end-to-end files (tools, training) take minutes on a busy two-core machine.
    common = dict(
        srcs = [src, _RUNNER],
        main = _RUNNER,
        python_version = "PY3",
        srcs_version = "PY3",
        deps = deps + ["//tests:conftest"],
        data = data + ["//:pytest.ini"],
        timeout = timeout,
        **kwargs
    )
    location = "$(rootpath %s)" % src
    if fast:
        native.py_test(name = name, args = ["-m", "'not slow'", location], tags = tags, **common)
    if slow:
        native.py_test(name = name + "_slow", args = ["-m", "slow", location], tags = tags + ["slow"], **common)
