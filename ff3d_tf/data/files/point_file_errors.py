"""The one error of a user's own point and pose files, shared by `point_files` and its PCD/PLY parsers (`pcd_ply`)."""
from __future__ import annotations


class PointFileError(ValueError):
    """A point or pose file that cannot be used: names the file, the field (or part of the file) and the problem."""

    def __init__(self, path: str, field: str, reason: str):
        self.path, self.field, self.reason = path, field, reason
        super().__init__(f"{path}: {field}: {reason}")
