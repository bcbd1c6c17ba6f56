"""Deterministic tar packing of in-memory members, recording where each member's data starts.

The tar is POSIX pax (plain ustar headers unless a name exceeds 100 characters); every header has
mtime 0, uid/gid 0, empty uname/gname, mode 0644, so equal input gives equal bytes.
"""

from __future__ import annotations

import io
import tarfile


def pack_tar(members: list[tuple[str, bytes]]) -> tuple[bytes, dict[str, tuple[int, int]]]:
    """Tar bytes of `(name, data)` members in the given order, and name -> (data offset, nbytes)."""
    buf = io.BytesIO()
    spans: dict[str, tuple[int, int]] = {}
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for name, data in members:
            if name in spans:
                raise ValueError(f"duplicate tar member name {name!r}")
            info = tarfile.TarInfo(name)
            info.size = len(data)
            info.mtime = 0
            info.mode = 0o644
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            info.type = tarfile.REGTYPE
            tar.addfile(info, io.BytesIO(data))
            padded = -(-len(data) // tarfile.BLOCKSIZE) * tarfile.BLOCKSIZE
            spans[name] = (tar.offset - padded, len(data))
    return buf.getvalue(), spans
