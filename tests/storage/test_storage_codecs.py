"""Member codecs: exact round trips for any valid array, decoding from the metadata text alone, errors."""

from __future__ import annotations

import lzma

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage import MEMBERS, DatasetFormatError, InvalidFrameError
from nuplan_occ.storage.codecs import decode, encode

ODD = GridSpec(0.0, 1.25, 0.0, 1.75, 0.0, 0.75, 0.25)  # 5 x 7 x 3: 105 voxels, not a multiple of 8
SMALL = GridSpec(-4.0, 4.0, -4.0, 4.0, -1.0, 1.0, 0.25)  # 32 x 32 x 8
MASKS = [name for name, spec in MEMBERS.items() if spec.packbits]


def _structured_mask(grid: GridSpec, rng: np.random.Generator, kind: str) -> np.ndarray:
    """Masks like the real ones (runs along z, blobs in x-y) and the extremes."""
    shape = grid.shape
    if kind == "empty":
        return np.zeros(shape, dtype=bool)
    if kind == "full":
        return np.ones(shape, dtype=bool)
    if kind == "random":
        return rng.random(shape) < rng.random()
    lo = rng.integers(0, shape[2], shape[:2])
    hi = lo + rng.integers(0, shape[2] + 1, shape[:2])
    z = np.arange(shape[2])
    return (z >= lo[..., None]) & (z < hi[..., None])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(["empty", "full", "random", "runs"]),
       member=st.sampled_from(MASKS), grid=st.sampled_from([ODD, SMALL]), level=st.integers(0, 9))
def test_masks_round_trip_exactly(seed, kind, member, grid, level):
    mask = _structured_mask(grid, np.random.default_rng(seed), kind)
    out = decode(MEMBERS[member], encode(MEMBERS[member], mask, level), grid, member)
    assert out.dtype == np.bool_ and out.shape == grid.shape and out.flags.writeable
    np.testing.assert_array_equal(out, mask)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), grid=st.sampled_from([ODD, SMALL]))
def test_dense_members_round_trip_exactly(seed, grid):
    rng = np.random.default_rng(seed)
    for name, spec in MEMBERS.items():
        if spec.packbits:
            continue
        info = np.iinfo(spec.dtype) if np.dtype(spec.dtype).kind == "u" else None
        shape = spec.shape(grid)
        array = (rng.integers(0, info.max, shape, endpoint=True).astype(spec.dtype) if info is not None
                 else rng.normal(0, 100, shape).astype(spec.dtype))
        out = decode(spec, encode(spec, array, 1), grid, name)
        assert out.dtype == array.dtype
        np.testing.assert_array_equal(out.view(np.uint8), array.view(np.uint8))  # bit-exact, NaNs included


def test_metadata_text_is_enough_to_decode_a_mask():
    """A reader that follows the `encoding` sentence with plain lzma + numpy gets the array back."""
    spec = MEMBERS["mask_lidar"]
    mask = _structured_mask(ODD, np.random.default_rng(1), "runs")
    entry = spec.describe(ODD, 6)
    assert entry["container"] == "xz" and entry["suffix"].endswith(".xz")
    assert "np.packbits" in entry["encoding"] and "C order" in entry["encoding"] and ".xz stream" in entry["encoding"]
    payload = lzma.decompress(encode(spec, mask, 6))
    assert len(payload) == 14  # ceil(105 / 8), as the encoding text states
    bits = np.unpackbits(np.frombuffer(payload, np.uint8), count=105).reshape(ODD.shape)
    np.testing.assert_array_equal(bits.astype(bool), mask)


def test_schema_v1_zstd_masks_still_decode():
    """Version-1 datasets stored the masks as packbits + zstd; the decoder tells containers by magic."""
    mask = _structured_mask(SMALL, np.random.default_rng(2), "runs")
    blob = zstandard.ZstdCompressor(level=3, write_content_size=True).compress(np.packbits(mask).tobytes())
    np.testing.assert_array_equal(decode(MEMBERS["mask_camera"], blob, SMALL, "v1"), mask)


@pytest.mark.parametrize("member", ["mask_lidar", "semantics"])
def test_corrupt_bytes_raise_format_error_naming_the_member(member):
    spec = MEMBERS[member]
    array = (_structured_mask(SMALL, np.random.default_rng(3), "runs") if spec.packbits
             else np.random.default_rng(3).integers(0, 15, SMALL.shape).astype(np.uint8))
    blob = encode(spec, array, 3)
    flipped = bytearray(blob)
    flipped[len(blob) // 2] ^= 0xFF
    other_grid = encode(spec, np.zeros(spec.shape(ODD), dtype=spec.dtype), 3)
    bad_blobs = [blob[: len(blob) // 2], b"garbage!" + blob, other_grid, b""]
    if spec.container == "xz":  # the stream's CRC32 catches any change; zstd members rely on the manifest crc32
        bad_blobs += [bytes(flipped), blob + b"\0"]
    for bad in bad_blobs:
        with pytest.raises(DatasetFormatError, match=f"frame-7.{member}"):
            decode(spec, bad, SMALL, f"frame-7.{member}")


def test_level_outside_the_container_range_is_rejected():
    with pytest.raises(InvalidFrameError, match="mask_lidar"):
        encode(MEMBERS["mask_lidar"], np.zeros(SMALL.shape, dtype=bool), 19)
