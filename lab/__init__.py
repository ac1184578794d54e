"""The lab: what measures rather than serves a user's job. The studies, benchmarks and profilers of ff3d_tf, the fault
soak, their timing and child-process harness (`bench`, `children`) and their tools (lab/tools/); the figures they
write are the repository's benchmarks/ (`paths.BENCHMARKS_DIR`, docs/benchmarks.md).

The lab imports ff3d_tf and tools/_common; ff3d_tf and tools/ never import the lab (tests/test_layout.py), and
`pip install .` does not ship it: run it from a checkout (the lab's tools put the checkout on sys.path).
"""
