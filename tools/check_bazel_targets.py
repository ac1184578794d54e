"""Check that the Bazel BUILD files cover the tree, so that `bazel test //...` runs every test and cannot rot.

    python tools/check_bazel_targets.py                   # exit 1, listing every missing or outdated entry
    python tools/check_bazel_targets.py --print-missing   # also print the BUILD stanzas to paste
    python tools/check_bazel_targets.py --fix             # rewrite the BUILD files of ff3d_tf/, lab/, tools/,
                                                          # tests/ and bazel/targets/

What it expects is derived from the sources (bazel/targets/expected.py says what): a `py_library` per module of
ff3d_tf/, lab/ and bazel/targets/, a `py_binary` per tool (tools/, lab/tools/), a `pytest_test` per test file, each
with the deps its imports need and the data the files it names need. The BUILD files are read as data, never run (bazel/targets/build_files.py
says which shapes it accepts; anything else is reported with its file and line). Targets whose source file is gone are
reported too. The library is bazel/targets/; this file is its command line.
"""
from __future__ import annotations

import argparse
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)  # bazel/targets/ (under Bazel, the runfiles root is on sys.path already)

from bazel.targets.compare import check  # noqa: E402 - needs ROOT on sys.path
from bazel.targets.expected import Tree  # noqa: E402
from bazel.targets.writer import fix, stanzas_by_build_file  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", default=ROOT, help="checkout to check (default: this one)")
    p.add_argument("--print-missing", action="store_true", help="print the BUILD stanzas that would fix the problems")
    p.add_argument("--fix", action="store_true",
                   help="rewrite the BUILD files of ff3d_tf/, lab/, tools/, tests/, bazel/targets/ to match the tree "
                        "(keeps comments at the top and attributes it does not derive, such as timeout or tags)")
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
