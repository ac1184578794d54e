"""FastFlow3D model (Keras 3)."""
from ff3d_tf.model.fastflow3d import FastFlow3D, build_model  # noqa: F401
