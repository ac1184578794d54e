"""Data path: WOD decoding, frame pairing, synthetic WOD-format segments, Argoverse 2 reader."""
