"""Reading the manifest: every published manifest file of a root as one row space, resolved to the
visible rows (`fragments.visible_rows`: per shard, its newest commit) in manifest order (log_id,
timestamp_us, frame_index, token).

Opening is one pass over the files (`_each_file`), each giving its footer and its index columns
together: shard, scene_token, commit_id and status read dictionary-encoded and kept as int codes,
log_id, timestamp_us and frame_index as int64; tokens are read only where those three keys tie. Other columns are read whole (`column`, `table`) or for chosen rows only (`take`: the
Parquet row groups holding them, a few kept in memory). A file folded away by a concurrent `compact`
between listing and reading makes opening retry with a fresh listing.

A damaged file (truncated, empty, not Parquet: its footer or index columns cannot be read) is skipped
and described in `ManifestIndex.damaged` (a `DamagedFile` each, also issued as a
`DamagedManifestWarning`): the rows of its shard resolve among the readable files, so they fall back to
the shard's previous commit where one is readable, else they are missing from the read result and the
`DamagedFile` says so. `strict=True` raises DatasetFormatError at the first damaged file instead.
Damage inside a column that opening does not read surfaces when that column is read, as a
DatasetFormatError naming the file.
"""

from __future__ import annotations

import itertools
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TypeVar

import fsspec
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from nuplan_occ.storage import keyorder
from nuplan_occ.storage.errors import DamagedManifestWarning, DatasetFormatError
from nuplan_occ.storage.fragments import (
    COMMIT_COLUMN, SHARDS_DIR, manifest_files, ranks_of_codes, shard_dir, visible_rows,
)
from nuplan_occ.storage.fsio import arrow_filesystem, is_local, resolve
from nuplan_occ.storage.manifest import SORT_KEYS, base_schema
from nuplan_occ.storage.records import STATUS_OK

OPEN_ATTEMPTS = 3
ROW_GROUP_CACHE = 8
REMOTE_READ_THREADS = 8
COMBINE_EVERY = 256
CODED_COLUMNS = ("shard", "scene_token", COMMIT_COLUMN, "status")
KEY_COLUMNS = SORT_KEYS[:3]
_NULL_KEY = np.iinfo(np.int64).max  # a null (unknown) key sorts after every known one, as in `ordered`
_CODED_TYPE = pa.dictionary(pa.int32(), pa.string())
_INDEX_SCHEMA = pa.schema([(c, _CODED_TYPE) for c in CODED_COLUMNS] + [(c, pa.int64()) for c in KEY_COLUMNS])
T = TypeVar("T")


def _column_order(schema: pa.Schema) -> pa.Schema:
    """Base and member columns in their fixed order, then the extras by name."""
    base = [n for n in base_schema(1).names if n in schema.names]
    extra = sorted(set(schema.names) - set(base))
    return pa.schema([schema.field(n) for n in base + extra])


@dataclass
class _FileIndex:
    """What opening reads of one manifest file: its schema (without metadata), rows per row group, and
    its index columns as `_INDEX_SCHEMA` (strings dictionary-encoded; a column the file lacks is null)."""

    schema: pa.Schema
    row_groups: np.ndarray
    columns: pa.Table


def _each_file(read: Callable[[int, bool], T], n_files: int, fs: fsspec.AbstractFileSystem) -> Iterator[T]:
    """read(i, use_threads) for every file i, in order. Local files are read one at a time (a single
    file with Arrow's own threads); remote ones `REMOTE_READ_THREADS` at a time (latency-bound)."""
    if is_local(fs) or n_files == 1:
        yield from (read(i, n_files == 1) for i in range(n_files))
        return
    with ThreadPoolExecutor(min(REMOTE_READ_THREADS, n_files)) as pool:
        yield from pool.map(lambda i: read(i, False), range(n_files))


def _concatenated(tables: Iterable[pa.Table]) -> pa.Table:
    """One table of one or more, combined `COMBINE_EVERY` at a time (thousands of tiny tables held
    their rows' memory again in per-table overhead)."""
    combined, pending = [], []
    for table in tables:
        pending.append(table)
        if len(pending) == COMBINE_EVERY:
            combined.append(pa.concat_tables(pending).combine_chunks())
            pending = []
    return pa.concat_tables(combined + pending)


def _parquet_errors(path: str, action: Callable[[], T], problem: str = "reading the manifest failed") -> T:
    """action(), with a damaged file raised as DatasetFormatError naming the file and `problem`
    (FileNotFoundError passes through)."""
    try:
        return action()
    except FileNotFoundError:
        raise
    except (pa.ArrowInvalid, OSError) as exc:
        raise DatasetFormatError(f"{path}: {problem} ({exc})") from exc


def _open_file(path: str, filesystem: pafs.FileSystem, use_threads: bool) -> _FileIndex:
    def read() -> _FileIndex:
        with filesystem.open_input_file(path) as handle:
            meta = pq.read_metadata(handle)
            schema = meta.schema.to_arrow_schema().remove_metadata()
            coded = [c for c in CODED_COLUMNS if c in schema.names]
            table = pq.ParquetFile(handle, metadata=meta, read_dictionary=coded).read(
                columns=[c for c in _INDEX_SCHEMA.names if c in schema.names], use_threads=use_threads)
        groups = np.array([meta.row_group(i).num_rows for i in range(meta.num_row_groups)], dtype=np.int64)
        return _FileIndex(schema, groups, _as_index_schema(table))
    return _parquet_errors(path, read, "not a readable Parquet file")


def _as_index_schema(table: pa.Table) -> pa.Table:
    """The index columns of one file's table in the types of `_INDEX_SCHEMA`."""
    arrays = []
    for field in _INDEX_SCHEMA:
        if field.name not in table.column_names:
            arrays.append(pa.nulls(table.num_rows, field.type))
        elif table[field.name].type == field.type:
            arrays.append(table[field.name])
        elif field.type == _CODED_TYPE:  # a string column stored otherwise (all null, large_string)
            arrays.append(pc.dictionary_encode(table[field.name].cast(pa.string())))
        else:
            arrays.append(table[field.name].cast(field.type))
    return pa.Table.from_arrays(arrays, schema=_INDEX_SCHEMA)


def _key_values(column: pa.ChunkedArray) -> np.ndarray:
    """int64 numpy of a key column, null = _NULL_KEY."""
    return (column.fill_null(_NULL_KEY) if column.null_count else column).to_numpy()


def _codes(column: pa.ChunkedArray) -> tuple[np.ndarray, pa.Array]:
    """(int32 code per row, -1 = null; distinct values) of a dictionary-encoded string column."""
    array = column.combine_chunks()  # one dictionary over every chunk (file and row group)
    indices = array.indices.fill_null(-1) if array.null_count else array.indices
    return indices.to_numpy().astype(np.int32, copy=False), array.dictionary


SUPERSEDED, FALLBACK, UNREADABLE = "superseded", "fallback", "unreadable"


@dataclass(frozen=True)
class DamagedFile:
    """A manifest file that cannot be read and is skipped. `shard_folder`: the shard folder it was
    published in (relative to manifest/shards; None for a compacted, scene or legacy file, which may hold
    any shard); `commit_id`: from its name (None for the legacy manifest.parquet). `outcome`:
    "superseded" (a newer commit of its shard is readable: nothing is missing), "fallback" (its shard's
    rows are those of the earlier commit `fallback_commit`) or "unreadable" (no readable commit of its
    shard(s): their frames are missing from the read result until they are rebuilt)."""

    path: str
    problem: str
    shard_folder: str | None
    commit_id: str | None
    outcome: str
    fallback_commit: str | None = None

    def describe(self) -> str:
        """One line naming the file, the problem and what readers see instead."""
        if self.outcome == SUPERSEDED:
            then = "a newer commit of its shard is read (nothing missing)"
        elif self.outcome == FALLBACK:
            then = f"its shard's rows are those of the earlier commit {self.fallback_commit} (rebuild to republish)"
        elif self.shard_folder is not None:
            then = "no earlier commit of its shard: the shard's frames are unreadable until it is rebuilt"
        else:
            then = "the frames it holds are unreadable unless a newer commit of their shard is readable"
        return f"{self.path}: unreadable manifest file skipped ({self.problem}); {then}"


class ManifestIndex:
    """The visible manifest rows of a dataset root, in manifest order; see the module docstring.

    `rows`: position in the files' row space of every visible row, in manifest order (int64);
    `scene_codes`: an int per visible row, equal within a scene_token, numbered in order of first
    appearance; a row of unknown scene (null scene_token) gets a code of its own, so clips never join
    frames of unknown scenes. `ok`: bool per visible row, status is "ok"; `frame_index`: int64 per
    visible row, -1 where unknown. `schema`: the union of the files' columns (a column a file lacks
    reads as null there). `paths`, `file_row_counts`: the manifest files read and their row counts
    (superseded rows included). `damaged`: the files skipped as unreadable (`DamagedFile`, see the module
    docstring); strict: raise DatasetFormatError at the first one instead.
    """

    def __init__(self, root: str, *, strict: bool = False):
        self.root = root
        self.strict = strict
        self._fs, self._path = resolve(root)
        self._cache: OrderedDict[tuple, pa.Table] = OrderedDict()
        self._footers: OrderedDict[int, pq.FileMetaData] = OrderedDict()
        for attempt in range(OPEN_ATTEMPTS):
            try:
                self._open()
                break
            except FileNotFoundError:
                if attempt == OPEN_ATTEMPTS - 1:
                    raise DatasetFormatError(f"{root}: manifest files keep vanishing while opening "
                                             "(a compaction running?); retry") from None
        for damaged in self.damaged:
            warnings.warn(damaged.describe(), DamagedManifestWarning, stacklevel=2)

    def _open(self) -> None:
        paths = manifest_files(self._fs, self._path)
        if not paths:
            raise DatasetFormatError(f"{self.root}: no manifest (nothing committed?)")
        self._filesystem = arrow_filesystem(self._fs)
        self.paths = paths
        index, problems = self._scan()
        codes = {c: _codes(index[c]) for c in CODED_COLUMNS}
        self.damaged = [self._damaged(path, problem, codes["shard"], codes[COMMIT_COLUMN])
                        for path, problem in problems]
        keys = {c: _key_values(index[c]) for c in KEY_COLUMNS}
        del index
        keep = _visible(codes["shard"], codes[COMMIT_COLUMN], self.file_row_counts)
        everything = len(keep) == self._file_start[-1]
        kept = [keys[c] if everything else keys[c][keep] for c in KEY_COLUMNS]
        del keys
        order = self._manifest_order(kept, keep)
        self._in_file_order = everything and order is None
        self.rows = keep if order is None else keep[order]

        def visible(values: np.ndarray) -> np.ndarray:
            return values if self._in_file_order else values[self.rows]

        frame_index = kept[KEY_COLUMNS.index("frame_index")]
        frame_index = frame_index if order is None else frame_index[order]
        self.frame_index = np.where(frame_index == _NULL_KEY, -1, frame_index)
        self.scene_codes = _scene_codes(visible(codes["scene_token"][0]))
        status, status_values = codes["status"]
        ok_code = status_values.index(STATUS_OK).as_py()
        self.ok = visible(status) == ok_code if ok_code >= 0 else np.zeros(len(self.rows), dtype=bool)

    def _scan(self) -> tuple[pa.Table, list[tuple[str, str]]]:
        """The index columns of every readable file (`_INDEX_SCHEMA`), in file order, and (path, problem)
        of each damaged one; keeps only the readable files in `paths` and sets their schemas, row counts
        and row groups. Raises at the first damaged file when strict."""
        schemas: dict[pa.Schema, int] = {}  # distinct file schemas -> their number
        schema_of_file, self._group_starts = [], []
        readable, damaged = [], []

        def open_file(i: int, threads: bool) -> _FileIndex | DatasetFormatError:
            try:
                return _open_file(self.paths[i], self._filesystem, threads)
            except DatasetFormatError as exc:
                if self.strict:
                    raise
                return exc

        def columns() -> Iterator[pa.Table]:
            for path, part in zip(self.paths, _each_file(open_file, len(self.paths), self._fs)):
                if isinstance(part, DatasetFormatError):
                    damaged.append((path, str(part).removeprefix(f"{path}: ")))
                    continue
                readable.append(path)
                schema_of_file.append(schemas.setdefault(part.schema, len(schemas)))
                self._group_starts.append(np.concatenate([[0], np.cumsum(part.row_groups)]))
                yield part.columns

        index = _concatenated(itertools.chain(columns(), [_INDEX_SCHEMA.empty_table()]))
        if not readable:
            raise DatasetFormatError(f"{damaged[0][0]}: {damaged[0][1]}; no manifest file of {self.root} "
                                     "is readable")
        self.paths = readable
        self._schema_of_file = np.array(schema_of_file, dtype=np.int64)
        self.file_row_counts = np.array([int(g[-1]) for g in self._group_starts], dtype=np.int64)
        self._file_start = np.concatenate([[0], np.cumsum(self.file_row_counts)])
        distinct = list(schemas)
        try:
            schema = pa.unify_schemas(distinct, promote_options="permissive")
        except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
            raise DatasetFormatError(f"{self.root}: manifest files have clashing column types ({exc})") from exc
        if COMMIT_COLUMN not in schema.names:
            schema = schema.append(pa.field(COMMIT_COLUMN, pa.string()))
        self.schema = _column_order(schema)
        self._file_columns = [set(s.names) for s in distinct]
        return index, damaged

    def _damaged(self, path: str, problem: str, shards: tuple[np.ndarray, pa.Array],
                 commits: tuple[np.ndarray, pa.Array]) -> DamagedFile:
        """What a damaged file means for its shard, from the readable rows' shard and commit codes."""
        folder, name = path.rsplit("/", 1)
        commit = name.removesuffix(".parquet") if path.startswith(f"{self._path}/manifest/") else None
        shards_top = f"{self._path}/{SHARDS_DIR}/"
        if not folder.startswith(shards_top):
            return DamagedFile(path, problem, None, commit, UNREADABLE)
        shard_codes, shard_values = shards
        same_folder = [k for k, v in enumerate(shard_values.to_pylist()) if shard_dir(self._path, v) == folder]
        commit_codes, commit_values = commits
        found = np.unique(commit_codes[np.isin(shard_codes, same_folder)])
        readable = sorted(commit_values.take(pa.array(found[found >= 0])).to_pylist())
        newer = [c for c in readable if c > commit]
        older = [c for c in readable if c < commit]
        outcome = SUPERSEDED if newer else FALLBACK if older else UNREADABLE
        return DamagedFile(path, problem, folder.removeprefix(shards_top), commit, outcome,
                           older[-1] if outcome == FALLBACK else None)

    def _read(self, columns: list[str]) -> pa.Table:
        """`columns` of every file, in file order; a column a file lacks reads as null."""
        return _concatenated(_each_file(lambda f, threads: self._file_table(f, columns, threads), len(self.paths),
                                        self._fs))

    def _file_table(self, f: int, columns: list[str], use_threads: bool, row_group: int | None = None) -> pa.Table:
        """`columns` of file f (or of its row group `row_group`) in the types of `schema`; a column the
        file lacks reads as null."""
        names = self._file_columns[self._schema_of_file[f]]
        present = [c for c in columns if c in names]
        path = self.paths[f]

        def read() -> pa.Table:
            with self._filesystem.open_input_file(path) as handle:
                if row_group is None:
                    return pq.ParquetFile(handle).read(columns=present, use_threads=use_threads)
                file = pq.ParquetFile(handle, metadata=self._footer(f, handle))
                return file.read_row_group(row_group, columns=present, use_threads=use_threads)

        table = _parquet_errors(path, read)
        schema = pa.schema([self.schema.field(c) for c in columns])
        arrays = [table[c] if c in names else pa.nulls(table.num_rows, schema.field(c).type) for c in columns]
        table = pa.Table.from_arrays(arrays, names=columns)
        return table if table.schema.equals(schema) else table.cast(schema)

    def _footer(self, f: int, handle: pa.NativeFile) -> pq.FileMetaData:
        """Parquet footer of file f, the last few kept (row-group reads of one file reuse it)."""
        meta = self._footers.pop(f, None) or pq.read_metadata(handle)
        while len(self._footers) >= ROW_GROUP_CACHE:
            self._footers.popitem(last=False)
        self._footers[f] = meta
        return meta

    def _manifest_order(self, keys: list[np.ndarray], keep: np.ndarray) -> np.ndarray | None:
        """Order of the kept rows (their `keys`) by SORT_KEYS, None if they are in order already (token
        breaks ties only where the integer keys tie)."""
        order = None if keyorder.in_order(keys) else keyorder.lex_order(keys)
        if keyorder.has_ties(keys, order):
            tokens = self._read(["token"])["token"].take(pa.array(keep))
            table = pa.table({**{n: keys[i] for i, n in enumerate(KEY_COLUMNS)}, "token": tokens})
            order = pc.sort_indices(table, sort_keys=[(k, "ascending") for k in SORT_KEYS]).to_numpy()
        return order

    def __len__(self) -> int:
        return len(self.rows)

    def column(self, name: str, positions: np.ndarray | None = None) -> pa.Array:
        """Column `name` of the visible rows (or of `positions` into them), in manifest order."""
        return self.table([name], positions)[name].combine_chunks()

    def table(self, columns: list[str] | None = None, positions: np.ndarray | None = None) -> pa.Table:
        """The visible rows (or `positions` into them) with `columns` (None: all), in manifest order."""
        columns = list(self.schema.names) if columns is None else list(columns)
        missing = sorted(set(columns) - set(self.schema.names))
        if missing:
            raise DatasetFormatError(f"{self.root}: manifest has no column(s) {missing}")
        if positions is None and self._in_file_order:
            return self._read(columns)
        rows = self.rows if positions is None else self.rows[np.asarray(positions, dtype=np.int64)]
        if positions is None or len(rows) > len(self.rows) // 4:
            return self._read(columns).take(pa.array(rows))
        return self.take(rows, columns)

    def take(self, rows: np.ndarray, columns: list[str]) -> pa.Table:
        """Rows `rows` of the files' row space with `columns`, reading only the row groups holding them."""
        file_of = np.searchsorted(self._file_start, rows, side="right") - 1
        pieces, where = [], np.empty(len(rows), dtype=np.int64)
        filled = 0
        for f in np.unique(file_of):
            in_file = np.flatnonzero(file_of == f)
            local = rows[in_file] - self._file_start[f]
            group_of = np.searchsorted(self._group_starts[f], local, side="right") - 1
            for g in np.unique(group_of):
                sel = in_file[group_of == g]
                table = self._row_group(int(f), int(g), columns)
                pieces.append(table.take(pa.array(local[group_of == g] - self._group_starts[f][g])))
                where[sel] = np.arange(filled, filled + len(sel))
                filled += len(sel)
        if not pieces:
            return self.schema.empty_table().select(columns)
        return pa.concat_tables(pieces).take(pa.array(where))

    def _row_group(self, f: int, g: int, columns: list[str]) -> pa.Table:
        key = (f, g, tuple(columns))
        table = self._cache.pop(key, None)
        if table is None:
            try:
                table = self._file_table(f, columns, use_threads=True, row_group=g)
            except FileNotFoundError as exc:
                raise DatasetFormatError(f"{self.paths[f]}: manifest file vanished (compacted since this "
                                         "dataset was opened?); open the dataset again") from exc
            while len(self._cache) >= ROW_GROUP_CACHE:
                self._cache.popitem(last=False)
        self._cache[key] = table
        return table


def _visible(shards: tuple[np.ndarray, pa.Array], commits: tuple[np.ndarray, pa.Array],
             file_row_counts: np.ndarray) -> np.ndarray:
    """Positions (int64, ascending) of the visible rows (`fragments.visible_rows`), given the merged
    codes of the shard and commit_id columns and the files' row counts."""
    shard_codes, shard_values = shards
    if len(shard_codes) and shard_codes.min() < 0:  # rows without a shard: one shard of their own
        shard_codes = np.where(shard_codes >= 0, shard_codes, len(shard_values))
    return np.flatnonzero(visible_rows(shard_codes, ranks_of_codes(*commits), file_row_counts))


def _scene_codes(codes: np.ndarray) -> np.ndarray:
    """int64 code per row from scene_token codes (-1 = null): dense, in order of first appearance;
    each null gets a code of its own, after the known ones."""
    n_values = int(codes.max()) + 1 if len(codes) else 0
    first = np.full(n_values + 1, len(codes), dtype=np.int64)
    np.minimum.at(first, codes, np.arange(len(codes)))  # first[-1]: the nulls'
    present = np.flatnonzero(first[:n_values] < len(codes))
    rank = np.empty(n_values + 1, dtype=np.int64)
    rank[present[np.argsort(first[present])]] = np.arange(len(present))
    result = rank[codes]
    unknown = np.flatnonzero(codes < 0)
    result[unknown] = len(present) + np.arange(len(unknown))
    return result


def read_manifest(root: str, columns: list[str] | None = None, *, strict: bool = False) -> pa.Table:
    """The visible manifest rows of a dataset root (failed ones included), in manifest order; damaged
    manifest files are skipped with a DamagedManifestWarning each (strict: raise; see module docstring)."""
    return ManifestIndex(root, strict=strict).table(columns)
