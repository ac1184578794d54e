"""Loaded at start-up by every Python process that Bazel runs (bazel/venv_python3.sh puts this folder on PYTHONPATH).

`make install` installs ff3d_tf in editable mode: a finder in the venv resolves `ff3d_tf.<module>` to the checkout
whenever the module is missing from sys.path. Under Bazel, first-party code must come from the runfiles only, so that
a target that forgot a dep fails instead of silently importing the checkout's file. This removes that finder.
"""
import sys

sys.meta_path[:] = [finder for finder in sys.meta_path
                    if not getattr(finder, "__module__", "").startswith("__editable__")]
