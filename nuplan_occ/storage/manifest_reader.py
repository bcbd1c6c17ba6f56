"""Reading the manifest: every published manifest file of a root as one row space, resolved to the
visible rows (`fragments.visible_rows`: per shard, its newest commit) in manifest order (log_id, timestamp_us, frame_index, token).

`ManifestIndex` reads only the columns it is asked for: opening reads the few index columns that
resolution and ordering need; other columns are read whole (`column`) or for chosen rows only
(`take`: the Parquet row groups holding them, a few kept in memory). A file folded away by a
concurrent `compact` between listing and reading makes opening retry with a fresh listing.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from nuplan_occ.storage.errors import DatasetFormatError
from nuplan_occ.storage.fragments import COMMIT_COLUMN, commit_ranks, manifest_files, visible_rows
from nuplan_occ.storage.fsio import is_local, resolve
from nuplan_occ.storage.manifest import SORT_KEYS, base_schema

OPEN_ATTEMPTS = 3
ROW_GROUP_CACHE = 8


def _arrow_filesystem(fs) -> pafs.FileSystem:
    return pafs.LocalFileSystem() if is_local(fs) else pafs.PyFileSystem(pafs.FSSpecHandler(fs))


def _column_order(schema: pa.Schema) -> pa.Schema:
    """Base and member columns in their fixed order, then the extras by name."""
    base = [n for n in base_schema(1).names if n in schema.names]
    extra = sorted(set(schema.names) - set(base))
    return pa.schema([schema.field(n) for n in base + extra])


class ManifestIndex:
    """The visible manifest rows of a dataset root, in manifest order; see the module docstring.

    `rows`: position in the files' row space of every visible row, in manifest order (int64);
    `scene_codes`: an int per visible row, equal within a scene_token; a row of unknown scene (null
    scene_token) gets a code of its own, so clips never join frames of unknown scenes.
    `schema`: the union of the files' columns (a column a file lacks reads as null there).
    `paths`, `file_row_counts`: the manifest files read and their row counts (superseded rows included).
    """

    def __init__(self, root: str):
        self.root = root
        self._fs, self._path = resolve(root)
        for attempt in range(OPEN_ATTEMPTS):
            try:
                self._open()
                break
            except FileNotFoundError:
                if attempt == OPEN_ATTEMPTS - 1:
                    raise DatasetFormatError(f"{root}: manifest files keep vanishing while opening "
                                             "(a compaction running?); retry") from None
        self._cache: OrderedDict[tuple, pa.Table] = OrderedDict()

    def _open(self) -> None:
        paths = manifest_files(self._fs, self._path)
        if not paths:
            raise DatasetFormatError(f"{self.root}: no manifest (nothing committed?)")
        fmt = pads.ParquetFileFormat()
        filesystem = _arrow_filesystem(self._fs)
        footers = [_footer(p, filesystem) for p in paths]  # kept as counts only: 19 k footers are ~1 GB
        schemas = {str(schema): schema for schema, _ in footers}
        try:
            schema = pa.unify_schemas(list(schemas.values()), promote_options="permissive")
        except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
            raise DatasetFormatError(f"{self.root}: manifest files have clashing column types ({exc})") from exc
        if COMMIT_COLUMN not in schema.names:
            schema = schema.append(pa.field(COMMIT_COLUMN, pa.string()))
        self.paths = paths
        self.schema = _column_order(schema.remove_metadata())
        self._format, self._filesystem = fmt, filesystem
        self._file_columns = [set(schema.names) for schema, _ in footers]
        counts = np.array([int(groups.sum()) for _, groups in footers], dtype=np.int64)
        self.file_row_counts = counts
        self._file_start = np.concatenate([[0], np.cumsum(counts)])
        self._group_starts = [np.concatenate([[0], np.cumsum(groups)]) for _, groups in footers]
        index = self._read(["shard", "scene_token", COMMIT_COLUMN, *SORT_KEYS[:3]])
        file_of_row = np.repeat(np.arange(len(paths)), counts)
        shards = pc.dictionary_encode(index["shard"].combine_chunks()).indices.to_numpy()
        keep = np.flatnonzero(visible_rows(shards, commit_ranks(index[COMMIT_COLUMN]), file_of_row))
        self.rows = keep[self._manifest_order(index, keep)]
        self.scene_codes = _scene_codes(index["scene_token"].take(pa.array(self.rows)))
        self._in_file_order = len(self.rows) == self._file_start[-1] and bool(np.all(np.diff(self.rows) == 1))

    def _read(self, columns: list[str]) -> pa.Table:
        """`columns` of every file, in file order (one file at a time: the dataset scanner's readahead
        held several GB at 3.6 M rows); a column a file lacks reads as null."""
        schema = pa.schema([self.schema.field(c) for c in columns])
        pieces = []
        for path, names in zip(self.paths, self._file_columns):
            try:
                table = pq.read_table(path, columns=[c for c in columns if c in names], filesystem=self._filesystem)
            except FileNotFoundError:
                raise
            except (pa.ArrowInvalid, OSError) as exc:
                raise DatasetFormatError(f"{path}: reading the manifest failed ({exc})") from exc
            arrays = [table[c] if c in names else pa.nulls(table.num_rows, schema.field(c).type) for c in columns]
            pieces.append(pa.Table.from_arrays(arrays, names=columns).cast(schema))
        return pa.concat_tables(pieces)

    def _manifest_order(self, index: pa.Table, keep: np.ndarray) -> np.ndarray:
        """Order of the kept rows by SORT_KEYS (token breaks ties only where the integer keys tie)."""
        last = np.iinfo(np.int64).max  # a null (unknown) key sorts after every known one, as in `ordered`
        keys = [index[name].cast(pa.int64()).fill_null(last).to_numpy()[keep] for name in SORT_KEYS[:3]]
        stacked = np.stack(keys, axis=1) if len(keep) else np.zeros((0, 3), np.int64)
        if len(keep) < 2 or np.all(_lex_less_equal(stacked[:-1], stacked[1:])):
            order = np.arange(len(keep))
        else:
            order = np.lexsort(keys[::-1])
        sorted_keys = stacked[order]
        if len(keep) > 1 and np.any(np.all(sorted_keys[1:] == sorted_keys[:-1], axis=1)):
            tokens = self._read(["token"])["token"].take(pa.array(keep))
            table = pa.table({**{n: keys[i] for i, n in enumerate(SORT_KEYS[:3])}, "token": tokens})
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
                fragment = self._format.make_fragment(self.paths[f], self._filesystem, row_groups=[g])
                table = fragment.to_table(schema=self.schema, columns=columns)
            except FileNotFoundError as exc:
                raise DatasetFormatError(f"{self.paths[f]}: manifest file vanished (compacted since this "
                                         "dataset was opened?); open the dataset again") from exc
            while len(self._cache) >= ROW_GROUP_CACHE:
                self._cache.popitem(last=False)
        self._cache[key] = table
        return table


def _scene_codes(scene_tokens: pa.ChunkedArray) -> np.ndarray:
    """int64 code per row, equal within a scene_token; each null gets a code of its own."""
    encoded = pc.dictionary_encode(scene_tokens.combine_chunks())
    codes = encoded.indices.fill_null(-1).to_numpy().astype(np.int64)
    unknown = codes < 0
    codes[unknown] = len(encoded.dictionary) + np.arange(int(unknown.sum()))
    return codes


def _footer(path: str, filesystem: pafs.FileSystem) -> tuple[pa.Schema, np.ndarray]:
    """(Arrow schema, rows per row group) of a manifest file (FileNotFoundError passes through)."""
    try:
        with filesystem.open_input_file(path) as handle:
            meta = pq.ParquetFile(handle).metadata
            return meta.schema.to_arrow_schema(), np.array([meta.row_group(i).num_rows
                                                            for i in range(meta.num_row_groups)], dtype=np.int64)
    except FileNotFoundError:
        raise
    except (pa.ArrowInvalid, OSError) as exc:
        raise DatasetFormatError(f"{path}: not a readable Parquet file ({exc})") from exc


def _lex_less_equal(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a <= b in lexicographic order of the columns."""
    result = np.ones(len(a), dtype=bool)
    decided = np.zeros(len(a), dtype=bool)
    for k in range(a.shape[1]):
        less, greater = a[:, k] < b[:, k], a[:, k] > b[:, k]
        result[~decided & greater] = False
        decided |= less | greater
    return result


def read_manifest(root: str, columns: list[str] | None = None) -> pa.Table:
    """The visible manifest rows of a dataset root (failed ones included), in manifest order."""
    return ManifestIndex(root).table(columns)
