"""Exceptions raised on bad nuPlan input. Every one names the offending file (`.path`) and the problem."""

from __future__ import annotations

from pathlib import Path


class NuplanFormatError(Exception):
    """A nuPlan file (DB, PCD, pickle blob, GPKG, data folder) that cannot be read as the format says.

    path: the offending file or folder as a string; problem: what is wrong with it.
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        return (type(self), (self.path, self.problem))


class PointCloudError(NuplanFormatError):
    """A PCD blob that is malformed, truncated or of an unsupported kind (e.g. DATA ascii)."""


class MissingBlobError(NuplanFormatError):
    """A sensor_blobs folder or blob file that the DB refers to does not exist."""


class UnsafePickleError(NuplanFormatError):
    """A calibration pickle that references anything but lists, tuples, numbers or numpy arrays, or is corrupt."""


class SchemaError(NuplanFormatError):
    """A log DB that lacks a table, column or row the reader needs, or holds a value of the wrong kind."""


class DatabaseError(NuplanFormatError):
    """A log DB path that does not exist or is not an SQLite database."""


class MapError(NuplanFormatError):
    """A map root, GPKG file or map layer that is missing or cannot be read."""


class MissingLogError(NuplanFormatError):
    """A requested log (by name or path) that is not found under the data root."""


class OutsideDataRootError(NuplanFormatError):
    """A file name in a log (e.g. lidar_pc.filename) that is absolute or climbs out of its folder with '..';
    the file is never opened and the message never repeats the name. path: the log DB that names it."""


class PoseGapError(NuplanFormatError):
    """A frame time that no usable ego_pose rows bracket closely enough to interpolate a pose (rows missing,
    or dropped as non-finite or absurd). path: the log DB."""
