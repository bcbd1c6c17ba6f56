"""Exceptions of the on-disk dataset format; each names the file (and frame) it is about."""

from __future__ import annotations


class StorageError(Exception):
    """Base class of every error raised by `nuplan_occ.storage`."""


class InvalidFrameError(StorageError, ValueError):
    """Input handed to the writer breaks the format (dtype, shape, key, column, metadata)."""


class ChecksumError(StorageError):
    """The stored bytes of a member do not match the manifest's crc32 (or length)."""

    def __init__(self, shard: str, frame_key: str, member: str, expected: int, actual: int):
        self.shard, self.frame_key, self.member = shard, frame_key, member
        super().__init__(
            f"{shard}: member {member!r} of frame {frame_key!r}: crc32 {actual:#010x} != manifest {expected:#010x}"
        )


class DatasetFormatError(StorageError):
    """A published file (manifest, dataset.json, shard) is missing or does not follow the format."""


class MissingMemberError(StorageError, KeyError):
    """A reader asked for a member (e.g. `flow`) that a frame does not have; members are never faked."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0])


class StorageWriteError(StorageError, OSError):
    """Writing or publishing a file failed (disk full, quota, read-only folder): errno and strerror of the
    OS error, `filename` the path that was being published. The temp file is removed; what was published
    before stays as it was."""

    @classmethod
    def of(cls, exc: OSError, path: str) -> "StorageWriteError":
        """The error for `exc` raised while publishing `path`."""
        return cls(exc.errno, exc.strerror or str(exc), path)

    def __str__(self) -> str:
        reason = (self.strerror or "write failed").lower()
        return f"{self.filename}: {reason} (not written; what was published before is kept)"


class DamagedManifestWarning(UserWarning):
    """A manifest file cannot be read and is skipped (see `manifest_reader.DamagedFile`)."""
