"""Argoverse 2: the sensor-log reader (sweeps, poses, cuboids, the ground raster) and the scene-flow challenge's submission archives."""
