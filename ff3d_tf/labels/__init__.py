"""Label construction: per-point flow bootstrapped from tracked 3D boxes (`box_flow`), at scale with Beam
(`pipeline`)."""
