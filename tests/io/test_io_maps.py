"""GPKG map writer -> reader round trip in UTM, window queries, map lookup."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pyogrio
import pyogrio.raw
import pytest
import shapely

from nuplan_occ.io.errors import MapError
from nuplan_occ.io.maps import LABEL_LAYERS, NuplanMap, find_map, write_map_gpkg, write_map_root
from nuplan_occ.io.types import MapLayer

X0, Y0 = 664000.0, 3997000.0
EPSG = 32611


def _layers():
    road = [shapely.box(X0, Y0, X0 + 50, Y0 + 20),
            shapely.MultiPolygon([shapely.box(X0 + 100, Y0, X0 + 110, Y0 + 10),
                                  shapely.box(X0 + 200, Y0, X0 + 210, Y0 + 10)])]
    lines = [shapely.LineString([(X0, Y0), (X0 + 10.123, Y0 + 3.456)]),
             shapely.MultiLineString([[(X0, Y0), (X0 + 1, Y0 + 1)], [(X0 + 5, Y0), (X0 + 6, Y0 + 2)]])]
    return {
        "road_segments": MapLayer(np.array(road, dtype=object),
                                  {"lane_group_fids": np.array(["1 2", "3"]), "width": np.array([1.5, 2.5])}),
        "boundaries": MapLayer(np.array(lines, dtype=object),
                               {"fid": np.array([7, 9]), "boundary_type_fid": np.array([0, 2])}),
        "traffic_lights": MapLayer(np.array([shapely.Point(X0 + 3.25, Y0 + 4.75)], dtype=object), {}),
    }


@pytest.fixture(scope="module")
def map_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("maps")
    write_map_root(root, "us-nv-las-vegas-strip", "9.15.1915", EPSG, _layers())
    write_map_root(root, "us-nv-las-vegas-strip", "9.9.1", EPSG, {})
    return root


def test_round_trip_in_utm_within_a_millimetre(map_root):
    path = find_map(map_root, "us-nv-las-vegas-strip.gpkg")
    assert path.parent.name == "9.15.1915"  # numeric version order: 9.15 > 9.9
    gmap = NuplanMap(path)
    assert gmap.epsg == EPSG and gmap.layer_names == ["boundaries", "road_segments", "traffic_lights"]
    for name, want in _layers().items():
        got = gmap.layer(name)
        assert len(got) == len(want)
        for g, w in zip(got.geometries, want.geometries):
            assert g.geom_type == w.geom_type
            np.testing.assert_allclose(shapely.get_coordinates(g), shapely.get_coordinates(w), atol=1e-3, rtol=0)
    np.testing.assert_array_equal(gmap.layer("boundaries").attributes["fid"], [7, 9])
    np.testing.assert_array_equal(gmap.layer("boundaries").attributes["boundary_type_fid"], [0, 2])
    assert list(gmap.layer("road_segments").attributes["lane_group_fids"]) == ["1 2", "3"]
    assert len(gmap.layer("walkways")) == 0


def test_storage_is_lon_lat_with_meta_table(map_root):
    path = find_map(map_root, "us-nv-las-vegas-strip")
    db = sqlite3.connect(path)
    assert dict(db.execute("SELECT key, value FROM meta").fetchall()) == {
        "geographicCoordSystem": "epsg:4326", "projectedCoordSystem": f"epsg:{EPSG}"}
    assert db.execute("SELECT DISTINCT srs_id FROM gpkg_geometry_columns").fetchall() == [(4326,)]
    db.close()
    meta, _, wkb, _ = pyogrio.raw.read(path, layer="traffic_lights")
    lon, lat = shapely.get_coordinates(shapely.from_wkb(wkb))[0]
    assert meta["crs"] == "EPSG:4326" and -116 < lon < -114 and 35 < lat < 37  # Las Vegas
    assert "meta" in [name for name, _ in pyogrio.list_layers(path)]
    index = json.loads((map_root / "nuplan-maps-v1.0.json").read_text())
    assert index["us-nv-las-vegas-strip"]["version"] == "9.9.1"  # last written entry


def test_layers_in_window(map_root):
    gmap = NuplanMap(find_map(map_root, "us-nv-las-vegas-strip"))
    found = gmap.layers_in_window(np.array([X0 + 105, Y0 + 5]), 3.0)
    assert set(found) == set(LABEL_LAYERS)
    assert len(found["road_segments"]) == 1 and found["road_segments"].geometries[0].geom_type == "MultiPolygon"
    assert list(found["road_segments"].attributes["lane_group_fids"]) == ["3"]
    assert len(found["boundaries"]) == 0 and len(found["walkways"]) == 0
    near_origin = gmap.layers_in_window(np.array([X0 + 2, Y0 + 1]), 2.0, names=("boundaries", "road_segments"))
    assert list(near_origin["boundaries"].attributes["fid"]) == [7, 9] and len(near_origin["road_segments"]) == 1


def test_map_errors(tmp_path):
    with pytest.raises(MapError) as err:
        find_map(tmp_path, "sg-one-north")
    assert err.value.path == str(tmp_path / "sg-one-north")
    with pytest.raises(MapError, match="not found"):
        NuplanMap(tmp_path / "absent.gpkg")
    bad = tmp_path / "bad.gpkg"
    bad.write_bytes(b"garbage" * 50)
    with pytest.raises(MapError) as err:
        NuplanMap(bad)
    assert err.value.path == str(bad)
    no_meta = tmp_path / "no_meta.gpkg"
    write_map_gpkg(no_meta, EPSG, _layers())
    db = sqlite3.connect(no_meta)
    with db:
        db.execute("UPDATE meta SET value = 'utm' WHERE key = 'projectedCoordSystem'")
    db.close()
    with pytest.raises(MapError, match="projectedCoordSystem"):
        NuplanMap(no_meta)
