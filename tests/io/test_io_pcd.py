"""PCD reader: header-driven layouts, the devkit-compatible writer, and fuzzing of header and body."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nuplan_occ.io.errors import PointCloudError
from nuplan_occ.io.pcd import MAX_HEADER_BYTES, encode_pcd, read_pcd
from nuplan_occ.io.types import PointCloud

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_NP_KIND = {"F": "f", "I": "i", "U": "u"}


def _header(fields, sizes, types, n, data="binary", counts=None, extra=""):
    counts = counts or ["1"] * len(fields)
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\n"
            f"TYPE {' '.join(types)}\nCOUNT {' '.join(counts)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"{extra}POINTS {n}\nDATA {data}\n").encode()


def _cloud(n, rng):
    return PointCloud(xyz=rng.normal(0, 30, (n, 3)), intensity=rng.uniform(0, 255, n).astype(np.float32),
                      ring=rng.integers(0, 128, n).astype(np.int16), lidar_info=rng.integers(0, 5, n).astype(np.int8),
                      frame="lidar")


def test_encode_matches_reference_header_and_round_trips():
    cloud = _cloud(7, np.random.default_rng(0))
    buf = encode_pcd(cloud)
    assert buf.startswith(b"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity ring "
                          b"lidar_info\nSIZE 4 4 4 4 4 4\nTYPE F F F F F F\nCOUNT 1 1 1 1 1 1\nWIDTH 7\nHEIGHT 1\n"
                          b"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 7\nDATA binary\n")
    assert len(buf) == buf.index(b"DATA binary\n") + 12 + 7 * 24
    back = read_pcd(buf + b"\x00" * 13, "mem.pcd")  # trailing garbage is ignored
    np.testing.assert_allclose(back.xyz, cloud.xyz.astype(np.float32))
    np.testing.assert_array_equal(back.ring, cloud.ring)
    np.testing.assert_array_equal(back.lidar_info, cloud.lidar_info)
    assert back.xyz.dtype == np.float64 and back.ring.dtype == np.int16 and back.lidar_info.dtype == np.int8
    assert len(read_pcd(encode_pcd(_cloud(0, np.random.default_rng(1))), "empty.pcd")) == 0
    with pytest.raises(ValueError):
        encode_pcd(PointCloud(cloud.xyz, cloud.intensity, cloud.ring, cloud.lidar_info, "ego"))


def test_mixed_types_and_missing_optional_fields():
    records = np.zeros(3, dtype=[("x", "<f8"), ("y", "<f4"), ("z", "<f2"), ("ring", "<u1"), ("lidar_info", "<i2")])
    records["x"], records["y"], records["z"] = [1, 2, 3], [4, 5, 6], [7, 8, 9]
    records["ring"], records["lidar_info"] = [0, 255, 3], [4, 9, -2]
    buf = _header(["x", "y", "z", "ring", "lidar_info"], [8, 4, 2, 1, 2], ["F", "F", "F", "U", "I"], 3) + records.tobytes()
    cloud = read_pcd(buf, "mixed.pcd")
    np.testing.assert_array_equal(cloud.xyz, [[1, 4, 7], [2, 5, 8], [3, 6, 9]])
    np.testing.assert_array_equal(cloud.ring, [0, 255, 3])
    np.testing.assert_array_equal(cloud.lidar_info, [4, -1, -1])  # outside 0..4 -> unknown
    np.testing.assert_array_equal(cloud.intensity, [-1, -1, -1])


def test_header_is_bounded():
    with pytest.raises(PointCloudError, match="no DATA line"):
        read_pcd(b"# " + b"x" * (2 * MAX_HEADER_BYTES) + b"\nDATA binary\n", "huge.pcd")
    with pytest.raises(PointCloudError, match="no DATA line"):
        read_pcd(b"# comment\n" * (MAX_HEADER_BYTES // 8), "many_lines.pcd")


@st.composite
def layouts(draw):
    """A random valid record layout, its PCD header and a body of random bytes (plus optional trailing bytes)."""
    names = ["x", "y", "z"] + draw(st.lists(st.sampled_from(["intensity", "ring", "lidar_info", "t", "rgb"]),
                                            unique=True, max_size=4))
    names = draw(st.permutations(names))
    types = [draw(st.sampled_from("FIU")) for _ in names]
    sizes = [draw(st.sampled_from([2, 4, 8] if t == "F" else [1, 2, 4, 8])) for t in types]
    n = draw(st.integers(0, 40))
    dtype = np.dtype([(f, f"<{_NP_KIND[t]}{s}") for f, t, s in zip(names, types, sizes)])
    body = draw(st.binary(min_size=n * dtype.itemsize, max_size=n * dtype.itemsize))
    trailing = draw(st.binary(max_size=16))
    return _header(names, sizes, types, n), dtype, n, body, trailing


@FUZZ
@given(layouts())
def test_fuzz_valid_layouts_match_numpy(layout):
    header, dtype, n, body, trailing = layout
    cloud = read_pcd(header + body + trailing, "fuzz.pcd")
    records = np.frombuffer(body, dtype=dtype, count=n)
    assert len(cloud) == n and cloud.frame == "lidar"
    with np.errstate(all="ignore"):
        want = np.stack([records[a].astype(np.float64) for a in "xyz"], axis=1).reshape(n, 3)
    np.testing.assert_array_equal(cloud.xyz, want)
    assert cloud.lidar_info.min(initial=0) >= -1 and cloud.lidar_info.max(initial=0) <= 4
    assert cloud.ring.min(initial=0) >= -1


@FUZZ
@given(layouts(), st.data())
def test_fuzz_damaged_bodies_only_raise_point_cloud_error(layout, data):
    header, _, n, body, trailing = layout
    cut = data.draw(st.integers(0, len(header) + len(body)))
    buf = (header + body)[:cut]
    try:
        cloud = read_pcd(buf, "cut.pcd")
    except PointCloudError as exc:
        assert exc.path == "cut.pcd"
    else:
        assert cut == len(header) + len(body) and len(cloud) == n


_HEADER_TOKENS = st.sampled_from(
    ["VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA", "x", "y", "z",
     "intensity", "binary", "ascii", "F", "I", "U", "0", "1", "2", "3", "4", "8", "-1", "1e9", "99999999999", "#",
     "\t", "\x00", "é"])


@FUZZ
@given(st.lists(st.lists(_HEADER_TOKENS, max_size=8), max_size=12), st.binary(max_size=200))
def test_fuzz_random_headers_only_raise_point_cloud_error(lines, body):
    buf = "\n".join(" ".join(words) for words in lines).encode("utf-8") + b"\n" + body
    try:
        read_pcd(buf, "random.pcd")
    except PointCloudError as exc:
        assert exc.path == "random.pcd"


@FUZZ
@given(st.binary(max_size=600), st.integers(0, 300), st.binary(max_size=8))
def test_fuzz_byte_mutations_of_a_real_header(noise, position, patch):
    base = bytearray(encode_pcd(_cloud(5, np.random.default_rng(3))))
    position = min(position, len(base))
    mutated = bytes(base[:position]) + patch + bytes(base[position + len(patch):]) + noise
    try:
        read_pcd(mutated, "mutated.pcd")
    except PointCloudError:
        pass


@pytest.mark.parametrize("header", [
    _header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 2, counts=["1", "1", "2"]),
    _header(["x", "y", "z"], [4, 4], ["F", "F", "F"], 2),
    _header(["x", "y", "y"], [4, 4, 4], ["F", "F", "F"], 2),
    _header(["x", "y", "intensity"], [4, 4, 4], ["F", "F", "F"], 2),
    _header(["x", "y", "z"], [4, 4, 1], ["F", "F", "F"], 2),
    _header(["x", "y", "z"], [4, 4, 3], ["F", "F", "I"], 2),
    _header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 2, data="ascii"),
    _header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 2, extra="POINTS 3\n"),
    b"VERSION 0.7\nFIELDS x y z\nDATA binary\n",
    b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS -2\nDATA binary\n",
])
def test_malformed_headers(header):
    with pytest.raises(PointCloudError):
        read_pcd(header + b"\x00" * 64, "bad.pcd")
