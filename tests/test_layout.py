"""The repository stands alone: no tracked file reads outside the clone (e.g. the developers' shared folder
beside it)."""
import os
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))  # the checkout, also under Bazel
NEEDLE = "../" + "shared"  # written in two parts so that this file does not match itself


def test_no_file_reads_outside_the_repository():
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    offenders = []
    for rel in tracked:
        if rel.startswith("data/") or not rel.endswith((".py", ".sh", ".yaml", ".md", "Makefile", "run", ".bzl",
                                                         "BUILD", "WORKSPACE", ".bazelrc")):
            continue
        with open(os.path.join(ROOT, rel), encoding="utf-8", errors="replace") as f:
            text = f.read()
        if NEEDLE in text:
            offenders.append(rel)
    assert not offenders, f"files that refer to {NEEDLE}: {offenders}"


def test_av2_sample_is_in_tree_with_its_notice():
    log = os.path.join(ROOT, "data", "av2_sample_log")
    assert os.path.isfile(os.path.join(log, "NOTICE.md"))
    assert len(os.listdir(os.path.join(log, "sensors", "lidar"))) == 2
