"""The reconstructed surface record: a triangle mesh (or the raw points for method "none")."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Surface:
    """A surface in the frame of the input points (`frame`, e.g. "scene" or "box"), metres.

    vertices: (V, 3) float64 holding float32 values: coordinates are rounded to float32 on construction
    (a shift of at most 0.03 mm within 500 m of the frame's origin, against 0.25 m voxels), so the stage
    cache stores them in 4 bytes each (pipeline.array_codec). faces: (F, 3) int64 indices into vertices;
    (0, 3) when the surface is a bare point set (method "none": vertices are then the raw input points).
    info: diagnostics of the method that made it (e.g. solver sizes); not part of the geometry.
    """

    vertices: np.ndarray
    faces: np.ndarray
    frame: str
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float32).astype(np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise ValueError(f"Surface: face indices out of range for {len(self.vertices)} vertices")

    @property
    def is_mesh(self) -> bool:
        """True when the surface has triangles."""
        return len(self.faces) > 0

    def with_triangles(self, vertices: np.ndarray, faces: np.ndarray, **info) -> "Surface":
        """This surface with the mesh (vertices (V', 3), faces (F', 3) into them, same frame) added, and `info`
        added to its info."""
        return Surface(np.vstack([self.vertices, vertices]), np.vstack([self.faces, faces + len(self.vertices)]),
                       self.frame, {**self.info, **info})

    def sample_points(self, spacing: float) -> np.ndarray:
        """Points (K, 3) in `frame` metres on the triangles, at most `spacing` apart along every
        triangle (a barycentric lattice per triangle fine enough for its longest edge).
        For a point-set surface the raw points are returned."""
        if spacing <= 0:
            raise ValueError(f"Surface.sample_points: spacing must be > 0, got {spacing}")
        if not self.is_mesh:
            return self.vertices.copy()
        tri = self.vertices[self.faces]  # (F, 3, 3)
        edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
        steps = np.maximum(1, np.ceil(edges / spacing).astype(np.int64))
        out = []
        for n in np.unique(steps):
            i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
            keep = i + j <= n
            bary = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], axis=1) / n  # (B, 3)
            sel = tri[steps == n]  # (T, 3, 3)
            out.append(np.einsum("bk,tkc->tbc", bary, sel).reshape(-1, 3))
        return np.concatenate(out, axis=0)
