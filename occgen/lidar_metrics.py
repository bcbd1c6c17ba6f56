"""Distribution metrics between sets of LiDAR sweeps: MMD and JSD on BEV histograms, Chamfer distance.

BEV occupancy histograms (the representation LiDAR-Diffusion's statistical metrics use, after LiDARGen
and Achlioptas et al.): the x, y coordinates of a sweep (metres, its own sensor / ego frame) are binned
into a `bins` x `bins` grid over [-extent, extent)^2 (default 100 x 100 cells of 1 m over +-50 m, points
outside dropped); the counts are normalized to sum to 1, so a sweep is a distribution over BEV cells.
    JSD(G, R) = Jensen-Shannon divergence (natural log, in [0, ln 2]) between the mean histogram of the
                generated set G and the mean histogram of the reference set R;
    MMD(G, R) = minimum matching distance: for each reference histogram, the squared L2 distance to its
                closest generated histogram, averaged over the reference set.
Chamfer distance between two clouds: mean nearest-neighbour distance from A to B plus from B to A (m).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from nuplan_occ.io.pcd import read_pcd


class SweepSetError(ValueError):
    """A folder of sweeps that is empty or does not match the other folder; names the folder."""

    def __init__(self, path: str | Path, problem: str):
        super().__init__(f"{path}: {problem}")


def bev_histogram(xyz: np.ndarray, bins: int = 100, extent: float = 50.0) -> np.ndarray:
    """Normalized (bins, bins) BEV histogram of points (N, 3) m; all zeros for an empty cloud."""
    h, _, _ = np.histogram2d(xyz[:, 0], xyz[:, 1], bins=bins, range=[[-extent, extent], [-extent, extent]])
    total = h.sum()
    return h / total if total > 0 else h


def jsd(gen_hists: np.ndarray, real_hists: np.ndarray) -> float:
    """JSD between the mean histograms of two stacks (n, bins, bins)."""
    p = gen_hists.mean(0).ravel()
    q = real_hists.mean(0).ravel()
    p, q = p / max(p.sum(), 1e-12), q / max(q.sum(), 1e-12)
    m = 0.5 * (p + q)

    def kl(a: np.ndarray) -> float:
        nz = a > 0
        return float((a[nz] * np.log(a[nz] / m[nz])).sum())

    return 0.5 * kl(p) + 0.5 * kl(q)


def mmd(gen_hists: np.ndarray, real_hists: np.ndarray) -> float:
    """Minimum matching distance (squared L2 between histograms) from each reference to the generated set."""
    g = gen_hists.reshape(len(gen_hists), -1)
    r = real_hists.reshape(len(real_hists), -1)
    d = (r * r).sum(1)[:, None] + (g * g).sum(1)[None] - 2.0 * r @ g.T
    return float(np.maximum(d, 0.0).min(1).mean())


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance (m) between clouds a (N, 3) and b (M, 3) in the same frame."""
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    return float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def sweep_metrics(gen: dict[str, np.ndarray], real: dict[str, np.ndarray]) -> dict:
    """MMD, JSD over all sweeps, Chamfer averaged over the names both sets hold (name -> xyz (N, 3))."""
    gh = np.stack([bev_histogram(x) for x in gen.values()])
    rh = np.stack([bev_histogram(x) for x in real.values()])
    common = sorted(set(gen) & set(real))
    return {
        "mmd": mmd(gh, rh),
        "jsd": jsd(gh, rh),
        "chamfer_m": float(np.mean([chamfer(gen[k], real[k]) for k in common])) if common else float("nan"),
        "n_generated": len(gen),
        "n_real": len(real),
        "n_paired": len(common),
    }


def _load_dir(folder: str | Path) -> dict[str, np.ndarray]:
    files = sorted(Path(folder).rglob("*.pcd"))
    if not files:
        raise SweepSetError(folder, "holds no .pcd files")
    return {str(f.relative_to(folder)): read_pcd(f.read_bytes(), str(f)).xyz for f in files}


def eval_lidar(generated_dir: str | Path, real_dir: str | Path) -> dict:
    """Metrics (see module docstring) between the .pcd sweeps of two folders; pairs by relative path."""
    return sweep_metrics(_load_dir(generated_dir), _load_dir(real_dir))
