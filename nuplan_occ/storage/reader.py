"""Ranged reads of shard members, checked against the manifest's crc32.

A `ShardReader` keeps one OS file descriptor per local shard (LRU-bounded) and reads with `os.pread`;
on object stores each read is one ranged GET (`fs.cat_file(path, start, end)`). Requests for members
of the same shard that lie close together (gap <= `coalesce_gap`) are served by a single read, so a
clip of consecutive frames in one shard costs one read. After a fork (DataLoader workers) the reader
drops the inherited descriptors and filesystem instance and reopens lazily in the new process.
"""

from __future__ import annotations

import os
import zlib
from collections import OrderedDict
from typing import NamedTuple

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import codecs
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import ChecksumError, DatasetFormatError, MissingMemberError
from nuplan_occ.storage.fsio import is_local, resolve
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.writer import shard_path


class BlobRequest(NamedTuple):
    """Where one member's compressed bytes are and what they must hash to."""

    shard: str
    offset: int
    nbytes: int
    crc32: int
    frame_key: str
    member: str


def request_of(row: dict, member: str) -> BlobRequest:
    """The read request of `member` in a manifest row; MissingMemberError if the frame lacks it."""
    if member not in MEMBERS:
        raise MissingMemberError(f"unknown member {member!r} (known: {list(MEMBERS)})")
    offset = row.get(f"{member}_offset")
    if offset is None:
        raise MissingMemberError(f"frame {row.get('key')!r} (shard {row.get('shard')!r}) has no {member!r} member")
    return BlobRequest(row["shard"], int(offset), int(row[f"{member}_nbytes"]), int(row[f"{member}_crc32"]),
                       row["key"], member)


class ShardReader:
    """Reads member bytes from the shards of one dataset root; see the module docstring."""

    def __init__(self, root: str, *, coalesce_gap: int = 1 << 20, max_open: int = 128):
        self.root = root
        self.coalesce_gap = coalesce_gap
        self.max_open = max_open
        self._fs, self._path = resolve(root)
        self._local = is_local(self._fs)
        self._pid = os.getpid()
        self._fds: OrderedDict[str, int] = OrderedDict()

    def __getstate__(self) -> dict:
        return {"root": self.root, "coalesce_gap": self.coalesce_gap, "max_open": self.max_open}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["root"], coalesce_gap=state["coalesce_gap"], max_open=state["max_open"])

    def __enter__(self) -> "ShardReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except TypeError:  # interpreter shutdown: module globals (os) are already gone
            pass

    def close(self) -> None:
        """Close the descriptors this process opened."""
        if getattr(self, "_pid", None) == os.getpid():
            for fd in self._fds.values():
                os.close(fd)
        self._fds = OrderedDict()

    def _after_fork(self) -> None:
        if os.getpid() != self._pid:
            for fd in self._fds.values():
                os.close(fd)  # this process's copy only; the parent's stays open
            self._fds = OrderedDict()
            self._fs, self._path = resolve(self.root)
            self._pid = os.getpid()

    def _fd(self, path: str) -> int:
        fd = self._fds.pop(path, None)
        if fd is None:
            fd = os.open(path, os.O_RDONLY)
            while len(self._fds) >= self.max_open:
                os.close(self._fds.popitem(last=False)[1])
        self._fds[path] = fd
        return fd

    def _read(self, shard: str, start: int, length: int) -> bytes:
        path = shard_path(self._path, shard)
        try:
            if self._local:
                data = os.pread(self._fd(path), length, start)
            else:
                data = self._fs.cat_file(path, start=start, end=start + length)
        except FileNotFoundError as exc:
            raise DatasetFormatError(f"{path}: shard named in the manifest is missing") from exc
        if len(data) != length:
            raise DatasetFormatError(f"{path}: read {len(data)} of {length} bytes at offset {start} (truncated)")
        return data

    def fetch(self, requests: list[BlobRequest]) -> list[bytes]:
        """Checked compressed bytes of each request, in request order (ChecksumError on mismatch)."""
        self._after_fork()
        out: list[bytes | None] = [None] * len(requests)
        order = sorted(range(len(requests)), key=lambda i: (requests[i].shard, requests[i].offset))
        group: list[int] = []
        for i in order:
            req = requests[i]
            if group:
                head, last = requests[group[0]], requests[group[-1]]
                if req.shard != head.shard or req.offset - (last.offset + last.nbytes) > self.coalesce_gap:
                    self._fetch_group(requests, group, out)
                    group = []
            group.append(i)
        if group:
            self._fetch_group(requests, group, out)
        return out  # type: ignore[return-value]

    def _fetch_group(self, requests: list[BlobRequest], group: list[int], out: list) -> None:
        start = requests[group[0]].offset
        end = max(requests[i].offset + requests[i].nbytes for i in group)
        data = memoryview(self._read(requests[group[0]].shard, start, end - start))
        for i in group:
            req = requests[i]
            blob = bytes(data[req.offset - start: req.offset - start + req.nbytes])
            actual = zlib.crc32(blob)
            if actual != req.crc32:
                raise ChecksumError(shard_path(self._path, req.shard), req.frame_key, req.member, req.crc32, actual)
            out[i] = blob


def decode_request(req: BlobRequest, blob: bytes, grid: GridSpec) -> np.ndarray:
    """Decoded array of a fetched member."""
    return codecs.decode(MEMBERS[req.member], blob, grid, f"shard {req.shard!r}, {req.frame_key}.{req.member}")


def read_member(root: str, row: dict, member: str, grid: GridSpec | None = None) -> np.ndarray:
    """One member of one manifest row: one ranged read, crc32 check, decode.

    grid: the dataset's grid; read from dataset.json when not given.
    """
    req = request_of(row, member)
    if grid is None:
        grid = GridSpec.from_dict(read_metadata(root)["grid"])
    with ShardReader(root) as reader:
        blob = reader.fetch([req])[0]
    return decode_request(req, blob, grid)
