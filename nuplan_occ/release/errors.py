"""Errors of the release import; each message is one line naming the file or folder."""

from __future__ import annotations


class ReleaseImportError(ValueError):
    """The import cannot go on (no release folder, unknown label id, options that contradict OUT)."""


class ReleaseFrameError(ValueError):
    """One release file is malformed; its frame gets a failed row with this message as the reason."""
