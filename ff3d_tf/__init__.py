"""ff3d_tf: FastFlow3D and the Waymo scene-flow dataset construction in TensorFlow (README.md, docs/)."""
from ff3d_tf import cpu as _cpu

_cpu.prefer_onednn()  # before TensorFlow starts: oneDNN's kernels on every x86 CPU (ff3d_tf.cpu)
