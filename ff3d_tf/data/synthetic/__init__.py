"""Synthetic data in each dataset's exact format (WOD segments, Argoverse 2 logs, own sweeps), made by the project's
own generators and read by the same code paths as the real data; ideal by default, or with a realistic sensor and
world (`realism`)."""
