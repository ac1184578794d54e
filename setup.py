"""ff3d_tf: FastFlow3D and Waymo scene-flow dataset construction in TensorFlow/Keras."""
from setuptools import find_packages, setup

setup(
    name="ff3d_tf",
    version="0.1.0",
    description="FastFlow3D (Jund et al., 'Scalable Scene Flow from Point Clouds in the Real World') in TF/Keras",
    packages=find_packages(include=["ff3d_tf", "ff3d_tf.*"]),
    python_requires=">=3.11",
    install_requires=[
        "tensorflow==2.21.0",
        "tensorboard==2.21.0",
        "numpy>=2,<3",
        "pyyaml>=6",
        "matplotlib>=3.8",
        "pyarrow>=14",  # Argoverse 2 feather files
        # waymo-open-dataset-tf-2-12-0==1.6.7 is installed with --no-deps by the Makefile (its pins downgrade TF).
    ],
    extras_require={
        "beam": ["apache-beam[tfrecord]==2.77.0"],
        "dev": ["pytest>=8", "pytest-xdist==3.8.0"],  # make test runs test files on 2 processes
        # Portable XLA export (tools/export_xla.py) and its TensorFlow-free runner (lab/tools/run_xla.py). jax 0.10.2 is
        # the newest that supports Python 3.11 and resolves against the TF 2.21 pins; a runner machine may have a
        # newer jax (artifacts stay loadable for 6 months of jaxlib releases, docs/deployment.md).
        "xla": ["jax==0.10.2", "jaxlib==0.10.2", "flatbuffers>=24.3.25"],
        # ONNX export for TensorRT and ONNX Runtime (tools/export_onnx.py) and its check against TensorFlow.
        "onnx": ["tf2onnx==1.17.0", "onnx==1.19.1", "onnxruntime==1.31.1"],
        # 3D recordings of clouds and flow for the Rerun viewer (tools/predict.py --rerun).
        "viz3d": ["rerun-sdk==0.41.0"],
        # Self-supervision's preparation (tools/prepare_self_supervision.py): DUFOMap's dynamic points and the
        # authors' HDBSCAN (scikit-learn 1.9.1's fails in its epsilon search on some sweeps; hdbscan pulls it in).
        "selfsup": ["dufomap==1.1.1", "hdbscan==0.8.44"],
        # Training and benchmarks on NVIDIA GPUs: the same TF with its CUDA libraries.
        "gpu": ["tensorflow[and-cuda]==2.21.0"],
    },
)
