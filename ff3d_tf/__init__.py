"""ff3d_tf: FastFlow3D and the Waymo scene-flow dataset construction in TensorFlow (README.md, docs/)."""
