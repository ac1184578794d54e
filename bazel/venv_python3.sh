#!/bin/sh
# Interpreter of the Bazel Python toolchain (bazel/BUILD): the project's virtualenv, made by `make install`, so Bazel
# runs the same pinned stack as `make test`. Bazel calls this file through a symlink in the runfiles tree; its real
# location gives the checkout, and Python finds .venv/pyvenv.cfg and the venv's site-packages from the interpreter path.
checkout="$(dirname "$(dirname "$(readlink -f "$0")")")"
venv_python="$checkout/.venv/bin/python3"
if [ ! -x "$venv_python" ]; then
    echo "bazel/venv_python3.sh: no virtualenv interpreter at $venv_python; run 'make install' first" >&2
    exit 1
fi
# bazel/hermetic/sitecustomize.py keeps the editable install of ff3d_tf from answering imports that the runfiles lack.
export PYTHONPATH="$checkout/bazel/hermetic${PYTHONPATH:+:$PYTHONPATH}"
exec "$venv_python" "$@"
