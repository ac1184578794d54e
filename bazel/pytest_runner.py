"""Main of the pytest targets of bazel/pytest.bzl: runs pytest on the files named on the command line.

Bazel starts it in the runfiles tree (the current directory), where pytest.ini and tests/conftest.py are runfiles of
every target, so pytest finds the same rootdir, markers and fixtures as `make test` does in the checkout.
"""
import os
import sys


def pytest_args(argv, env):
    """pytest's argument list for the target's own arguments `argv` (marker expression, files) in Bazel's test `env`."""
    args = ["-q", "-p", "no:cacheprovider", *argv]
    tmpdir = env.get("TEST_TMPDIR")
    if tmpdir:
        args += ["--basetemp", os.path.join(tmpdir, "pytest")]
    if env.get("XML_OUTPUT_FILE"):  # per-test-case results in Bazel's test.xml
        args += ["--junitxml", env["XML_OUTPUT_FILE"]]
    if env.get("TESTBRIDGE_TEST_ONLY"):  # bazel test --test_filter=EXPR selects tests by pytest's -k EXPR
        args += ["-k", env["TESTBRIDGE_TEST_ONLY"]]
    return args


def main():
    # Bazel runs tests without HOME; Keras and TensorFlow keep caches below it.
    if "HOME" not in os.environ and "TEST_TMPDIR" in os.environ:
        os.environ["HOME"] = os.environ["TEST_TMPDIR"]
    import pytest
    return pytest.main(pytest_args(sys.argv[1:], os.environ))


if __name__ == "__main__":
    sys.exit(main())
