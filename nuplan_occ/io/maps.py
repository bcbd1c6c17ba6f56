"""nuPlan GPKG maps: a pure-sqlite3 writer and a pyogrio-based reader.

Geometries are stored in EPSG:4326 (x = lon, y = lat) and exposed in the map's projected CRS, the UTM
zone named by the `meta` table's projectedCoordSystem row ("global" frame, metres), as the devkit does.
"""

from __future__ import annotations

import json
import re
import sqlite3
import struct
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyogrio
import pyogrio.raw
import shapely
from pyproj import CRS, Transformer

from nuplan_occ.io.errors import MapError
from nuplan_occ.io.types import MapLayer

LABEL_LAYERS: tuple[str, ...] = (
    "road_segments", "intersections", "generic_drivable_areas", "carpark_areas", "lanes_polygons", "walkways",
    "crosswalks", "boundaries", "stop_polygons",
)
"""Vector layers used for BEV semantics (road, other-ground, road-line)."""

MAP_VERSION_FILE = "nuplan-maps-v1.0.json"
_STORAGE_SRS = 4326
# gpkg_contents.last_change is a fixed date so the same layers always give the same bytes.
_GPKG_DDL = """
CREATE TABLE gpkg_spatial_ref_sys (
    srs_name TEXT NOT NULL, srs_id INTEGER NOT NULL PRIMARY KEY, organization TEXT NOT NULL,
    organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL, description TEXT);
CREATE TABLE gpkg_contents (
    table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL, identifier TEXT UNIQUE,
    description TEXT DEFAULT '', last_change DATETIME NOT NULL DEFAULT '2021-01-01T00:00:00.000Z',
    min_x DOUBLE, min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER REFERENCES gpkg_spatial_ref_sys(srs_id));
CREATE TABLE gpkg_geometry_columns (
    table_name TEXT NOT NULL, column_name TEXT NOT NULL, geometry_type_name TEXT NOT NULL, srs_id INTEGER NOT NULL,
    z TINYINT NOT NULL, m TINYINT NOT NULL, PRIMARY KEY (table_name, column_name));
CREATE TABLE meta (fid INTEGER PRIMARY KEY AUTOINCREMENT, key TEXT, value TEXT);
"""


# ---------------------------------------------------------------------------------------------- writer
def _quote(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _gpkg_blob(geometry: shapely.Geometry) -> bytes:
    """GeoPackageBinary: 'GP', version 0, flags (little-endian, xy envelope or empty), srs id, envelope, ISO WKB."""
    wkb = shapely.to_wkb(geometry, output_dimension=2, byte_order=1, flavor="iso")
    if geometry.is_empty:
        return b"GP" + bytes([0, 0b10001]) + struct.pack("<i", _STORAGE_SRS) + wkb
    minx, miny, maxx, maxy = shapely.bounds(geometry)
    return b"GP" + bytes([0, 0b11]) + struct.pack("<i4d", _STORAGE_SRS, minx, maxx, miny, maxy) + wkb


def _sql_type(values: np.ndarray) -> str:
    kind = np.asarray(values).dtype.kind
    return {"i": "INTEGER", "u": "INTEGER", "f": "REAL", "b": "BOOLEAN"}.get(kind, "TEXT")


def _sql_value(value: object) -> object:
    if value is None:
        return None
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value if isinstance(value, (int, float, str, bool)) else str(value)


def _geometry_type(geometries: np.ndarray) -> str:
    kinds = {shapely.get_type_id(g) for g in geometries}
    names = {0: "POINT", 1: "LINESTRING", 3: "POLYGON", 4: "MULTIPOINT", 5: "MULTILINESTRING", 6: "MULTIPOLYGON"}
    return names.get(kinds.pop(), "GEOMETRY") if len(kinds) == 1 else "GEOMETRY"


def _reproject(geometries: np.ndarray, source_crs: str, target_crs: str) -> np.ndarray:
    """2D geometries from one CRS to another (axis order x = easting / lon, y = northing / lat)."""
    transformer = Transformer.from_crs(source_crs, target_crs, always_xy=True)

    def move(xy: np.ndarray) -> np.ndarray:
        return np.column_stack(transformer.transform(xy[:, 0], xy[:, 1]))

    return shapely.transform(np.asarray(geometries, dtype=object), move)


def _write_layer(db: sqlite3.Connection, name: str, layer: MapLayer, epsg: int) -> None:
    if name in ("meta",) or name.startswith("gpkg_"):
        raise ValueError(f"reserved map layer name {name!r}")
    geometries = _reproject(layer.geometries, f"EPSG:{epsg}", f"EPSG:{_STORAGE_SRS}")
    for column, values in layer.attributes.items():
        if len(values) != len(geometries):
            raise ValueError(f"layer {name}: attribute {column} has {len(values)} values for {len(geometries)} features")
    columns = [c for c in layer.attributes if c != "fid"]
    column_sql = "".join(f", {_quote(c)} {_sql_type(layer.attributes[c])}" for c in columns)
    gtype = _geometry_type(geometries) if len(geometries) else "GEOMETRY"
    db.execute(f"CREATE TABLE {_quote(name)} (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom {gtype}{column_sql})")
    fids = layer.attributes.get("fid", np.arange(1, len(geometries) + 1))
    placeholders = ", ".join("?" * (len(columns) + 2))
    db.executemany(
        f"INSERT INTO {_quote(name)} (fid, geom{''.join(', ' + _quote(c) for c in columns)}) VALUES ({placeholders})",
        [(int(fids[i]), _gpkg_blob(g), *(_sql_value(layer.attributes[c][i]) for c in columns))
         for i, g in enumerate(geometries)],
    )
    bounds = shapely.total_bounds(geometries) if len(geometries) else np.full(4, np.nan)
    db.execute("INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', ?, ?, 0, 0)", (name, gtype, _STORAGE_SRS))
    db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, min_x, min_y, max_x, max_y, srs_id) "
               "VALUES (?, 'features', ?, ?, ?, ?, ?, ?)", (name, name, *map(_sql_value, bounds), _STORAGE_SRS))


def write_map_gpkg(path: str | Path, epsg: int, layers: dict[str, MapLayer]) -> None:
    """Write a GPKG map as nuPlan lays it out: geometries given in UTM EPSG:<epsg>, stored in EPSG:4326;
    a `meta` table with geographicCoordSystem epsg:4326 and projectedCoordSystem epsg:<epsg>.
    attributes become columns (an integer "fid" attribute, if given, sets the feature ids)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)
    db = sqlite3.connect(tmp)
    try:
        with db:
            db.execute("PRAGMA application_id = 1196444487")  # 0x47504B47 'GPKG'
            db.execute("PRAGMA user_version = 10200")
            db.executescript(_GPKG_DDL)
            db.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)", [
                ("Undefined cartesian SRS", -1, "NONE", -1, "undefined", None),
                ("Undefined geographic SRS", 0, "NONE", 0, "undefined", None),
                ("WGS 84 geodetic", _STORAGE_SRS, "EPSG", _STORAGE_SRS, CRS.from_epsg(_STORAGE_SRS).to_wkt("WKT1_GDAL"),
                 "longitude/latitude coordinates in decimal degrees on the WGS 84 spheroid"),
            ])
            db.executemany("INSERT INTO meta (key, value) VALUES (?, ?)",
                           [("geographicCoordSystem", f"epsg:{_STORAGE_SRS}"), ("projectedCoordSystem", f"epsg:{epsg}")])
            db.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier) VALUES ('meta', 'attributes', 'meta')")
            for name, layer in layers.items():
                _write_layer(db, name, layer, epsg)
    finally:
        db.close()
    tmp.replace(path)


def write_map_root(maps_root: str | Path, map_name: str, version: str, epsg: int,
                   layers: dict[str, MapLayer]) -> Path:
    """Write `<maps_root>/<map_name>/<version>/map.gpkg` and add the map to `<maps_root>/nuplan-maps-v1.0.json`
    (existing entries are kept). Returns the GPKG path."""
    root = Path(maps_root)
    gpkg = root / map_name / version / "map.gpkg"
    write_map_gpkg(gpkg, epsg, layers)
    index_path = root / MAP_VERSION_FILE
    index = json.loads(index_path.read_text()) if index_path.is_file() else {}
    index[map_name] = {"version": version, "layers": {}}
    index_path.write_text(json.dumps(index, indent=2, sort_keys=True))
    return gpkg


# ---------------------------------------------------------------------------------------------- reader
def _version_key(version: str) -> tuple:
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"[.\-_]", version))


def find_map(maps_root: str | Path, map_name: str) -> Path:
    """`<maps_root>/<map_name>/<version>/map.gpkg` of the newest version (numeric order); MapError if none.
    A '.gpkg' suffix on map_name (as in some log.map_version values) is ignored."""
    map_name = map_name[:-5] if map_name.endswith(".gpkg") else map_name
    candidates = sorted(Path(maps_root).glob(f"{map_name}/*/map.gpkg"), key=lambda p: _version_key(p.parent.name))
    if not candidates:
        raise MapError(Path(maps_root) / map_name, "no <version>/map.gpkg found for this map")
    return candidates[-1]


def usable_map(maps_root: str | Path, map_name: str) -> tuple[Path | None, str]:
    """The newest readable map of a log (`find_map`, then its GPKG layers and meta table opened) and "", or
    None and the one-line reason no map can be used (the MapError's text, naming the folder or file)."""
    try:
        path = find_map(maps_root, map_name)
        NuplanMap(path)
    except MapError as exc:
        return None, f"no usable map: {exc}; ground voxels keep the label other (no road, road_line or other_ground)"
    return path, ""


def _empty_layer() -> MapLayer:
    return MapLayer(geometries=np.empty(0, dtype=object), attributes={"fid": np.zeros(0, dtype=np.int64)})


class NuplanMap:
    """A nuPlan GPKG map. Layers are returned in the UTM frame (meta projectedCoordSystem), cached per layer.

    epsg: the projected CRS code; layer_names: the vector (feature) layers in the file.
    """

    def __init__(self, gpkg_path: str | Path):
        self.path = Path(gpkg_path)
        if not self.path.is_file():
            raise MapError(self.path, "map file not found")
        try:
            listed = pyogrio.list_layers(self.path)
            _, _, _, fields = pyogrio.raw.read(self.path, layer="meta", read_geometry=False)
        except Exception as exc:  # noqa: BLE001 - GDAL raises several types for unreadable files
            raise MapError(self.path, f"cannot read GPKG layers or its meta table ({exc})") from None
        meta = dict(zip(fields[0], fields[1]))
        projected = str(meta.get("projectedCoordSystem", ""))
        match = re.fullmatch(r"(?i)epsg:(\d+)", projected.strip())
        if match is None:
            raise MapError(self.path, f"meta table lacks an epsg:<code> projectedCoordSystem (got {projected!r})")
        self.epsg = int(match.group(1))
        self.layer_names = sorted(str(name) for name, gtype in listed if gtype is not None)
        self._layers: dict[str, MapLayer] = {}
        self._trees: dict[str, shapely.STRtree] = {}

    def layer(self, name: str) -> MapLayer:
        """A vector layer in UTM metres with its attribute columns (plus "fid", int64); a layer the file does
        not have is an empty MapLayer."""
        if name not in self._layers:
            self._layers[name] = self._read_layer(name) if name in self.layer_names else _empty_layer()
        return self._layers[name]

    def _read_layer(self, name: str) -> MapLayer:
        try:
            meta, fids, wkb, fields = pyogrio.raw.read(self.path, layer=name, return_fids=True, force_2d=True)
            geometries = shapely.from_wkb(wkb)
        except Exception as exc:  # noqa: BLE001 - GDAL / GEOS errors of a corrupt layer
            raise MapError(self.path, f"cannot read layer {name} ({exc})") from None
        if meta.get("crs") is None:
            raise MapError(self.path, f"layer {name} has no CRS")
        attributes = {str(col): np.asarray(values) for col, values in zip(meta["fields"], fields)}
        attributes["fid"] = np.asarray(fids, dtype=np.int64)
        return MapLayer(geometries=_reproject(geometries, meta["crs"], f"EPSG:{self.epsg}"), attributes=attributes)

    def _tree(self, name: str) -> shapely.STRtree:
        if name not in self._trees:
            self._trees[name] = shapely.STRtree(self.layer(name).geometries)
        return self._trees[name]

    def layers_in_window(self, center_xy: np.ndarray, half_size_m: float,
                         names: Sequence[str] = LABEL_LAYERS) -> dict[str, MapLayer]:
        """Features of each named layer that intersect the axis-aligned UTM square centre_xy ± half_size_m.

        Geometries are returned whole (not clipped), with their attribute rows.
        """
        cx, cy = np.asarray(center_xy, dtype=np.float64).reshape(-1)[:2]
        window = shapely.box(cx - half_size_m, cy - half_size_m, cx + half_size_m, cy + half_size_m)
        out = {}
        for name in names:
            layer = self.layer(name)
            if len(layer) == 0:
                out[name] = layer
                continue
            idx = np.sort(self._tree(name).query(window, predicate="intersects"))
            out[name] = MapLayer(geometries=layer.geometries[idx],
                                 attributes={k: v[idx] for k, v in layer.attributes.items()})
        return out
