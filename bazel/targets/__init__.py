"""The library of tools/check_bazel_targets.py (build tooling, not part of ff3d_tf).

- build_files: reads BUILD files as data (parsed with `ast`, never executed) and writes labels.
- sources: what a Python source needs, from its syntax tree (imports, named files, slow marks).
- expected: the target each first-party source needs, and its BUILD stanza.
- compare: the differences between those targets and the BUILD files.
- writer: the stanzas to paste, and the rewrite of the BUILD files (--fix).
"""
