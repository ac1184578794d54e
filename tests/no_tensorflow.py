"""Runs a script in a subprocess where TensorFlow and Keras cannot be imported: the JAX-only runners of the portable
XLA programs (`lab/tools/run_xla.py`, `lab/tools/run_nsfp_xla.py`) must work on a machine without them."""
import subprocess
import sys

from conftest import ROOT

NO_TF_SHIM = """
import runpy, sys
for name in ("tensorflow", "keras", "tf_keras"):
    sys.modules[name] = None  # an import of a None entry raises ImportError
try:
    import tensorflow
except ImportError:
    tensorflow = None
if tensorflow is not None:
    raise SystemExit("the shim failed to block tensorflow")
script, sys.argv = sys.argv[1], sys.argv[1:]
runpy.run_path(script, run_name="__main__")
"""


def run_without_tf(script_path: str, *args: str) -> str:
    """stdout of `python script_path args...` with TensorFlow unimportable; asserts that it exits 0."""
    out = subprocess.run([sys.executable, "-c", NO_TF_SHIM, script_path, *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout
