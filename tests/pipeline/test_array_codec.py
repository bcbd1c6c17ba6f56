"""The stage cache's array coding: every array comes back with its dtype, shape and bits, and arrays
whose values fit a narrower dtype are stored in it."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import zstandard

from nuplan_occ.pipeline.array_codec import dumps, narrowest_exact_dtype
from nuplan_occ.pipeline.cache import StageCache
from nuplan_occ.recon import Surface


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    exact = rng.normal(size=(5000, 3)).astype(np.float32).astype(np.float64)
    inexact = rng.normal(size=(5000, 3))
    with_nan = exact.copy()
    with_nan[::7, 1] = np.nan
    with_nan[::11, 2] = -0.0
    return {
        "exact_float32_values": exact, "full_float64": inexact, "nan_and_signed_zero": with_nan,
        "small_ints": rng.integers(-300, 300, size=(4000, 3)), "int32_range": rng.integers(0, 2**20, size=9000),
        "wide_ints": rng.integers(-2**40, 2**40, size=3000), "bools": rng.random(50_000) > 0.5,
        "uint8_3d": rng.integers(0, 255, size=(20, 30, 40), dtype=np.uint8),
        "transposed_view": inexact.T, "strided_view": exact[::2], "empty": np.zeros((0, 3)),
        "tiny": np.arange(5, dtype=np.float64),
    }


@pytest.mark.parametrize("name", list(_arrays()))
def test_roundtrip_is_bit_exact(name: str) -> None:
    original = _arrays()[name]
    restored = pickle.loads(dumps({"a": original}))["a"]
    assert restored.dtype == original.dtype and restored.shape == original.shape
    assert np.array_equal(np.ascontiguousarray(restored).view(np.uint8),
                          np.ascontiguousarray(original).view(np.uint8))


def test_narrowest_exact_dtype() -> None:
    arrays = _arrays()
    assert narrowest_exact_dtype(arrays["exact_float32_values"]) == np.float32
    assert narrowest_exact_dtype(arrays["nan_and_signed_zero"]) == np.float32
    assert narrowest_exact_dtype(arrays["full_float64"]) == np.float64
    assert narrowest_exact_dtype(arrays["small_ints"]) == np.int16
    assert narrowest_exact_dtype(arrays["int32_range"]) == np.int32
    assert narrowest_exact_dtype(arrays["wide_ints"]) == np.int64


def test_surface_entry_is_smaller_and_identical(tmp_path) -> None:
    """A mesh the size of a scene's background: float32-precision vertices and int64 faces take about
    half the bytes of the plain pickle at the same zstd level, and read back equal."""
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(300) * 0.25, np.arange(300) * 0.25, indexing="ij"), -1).reshape(-1, 2)
    vertices = np.column_stack([grid, rng.normal(0.0, 0.05, len(grid))])
    cells = (np.arange(299)[:, None] * 300 + np.arange(299)[None, :]).ravel()
    faces = np.concatenate([np.stack([cells, cells + 1, cells + 300], 1), np.stack([cells + 1, cells + 301, cells + 300], 1)])
    surface = Surface(vertices, faces, "scene")
    cache = StageCache(tmp_path)
    cache.put("reconstruct", "k", {"background_surface": surface})
    stored = next((tmp_path / "reconstruct").iterdir()).stat().st_size
    plain = len(zstandard.ZstdCompressor(level=3).compress(pickle.dumps({"background_surface": surface}, protocol=5)))
    assert stored < 0.6 * plain
    back = cache.get("reconstruct", "k")["background_surface"]
    assert np.array_equal(back.vertices, surface.vertices) and np.array_equal(back.faces, surface.faces)
    assert back.vertices.dtype == np.float64 and back.faces.dtype == np.int64


def test_surface_vertices_carry_float32_precision() -> None:
    vertices = np.array([[0.1, 250.123456789, -3.3], [1.0, 2.0, 3.0], [0.5, 0.25, 0.0]])
    surface = Surface(vertices, np.array([[0, 1, 2]]), "scene")
    assert np.array_equal(surface.vertices, vertices.astype(np.float32).astype(np.float64))
    assert np.abs(surface.vertices - vertices).max() < 3e-5
