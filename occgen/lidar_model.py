"""The learned LiDAR generator (paper section "LiDAR Generation with View Decoupling"), at CPU scale.

Frames: occupancy indexed [x, y, z] in the ego frame (rear axle, x forward, y left, z up); rays, origins
and depths in that frame (metres). Pipeline for a batch of rays of some LiDARs:
1. 3D encoder: the grid pooled by `pool` into per-class fractions (any / ground / road line / objects /
   other), a stride-2 3D conv stem, then blocks X + gate * AdaLN(Conv3D(X)) (AdaLN-Zero: scale, shift
   and gate come from the rig embedding through a zero-initialized linear). Dense convs replace the
   paper's Sparse UNet at this scale.
2. Rig embedding: the origin of each of the 5 LiDARs (lidar_info order) is Fourier-encoded; LiDARs
   not selected for the step are zeroed; an MLP ("resampling network") maps the concatenation to f_r.
   Each training step selects a random subset of LiDARs and uses only their rays.
3. Occupancy-prior sampling (occgen.lidar_sampling): the ray is marched at `march_step` through the
   label grid; `n_samples` points are drawn by inverse CDF from a PDF that is 1 on the march intervals
   around the first occupied point (the visible surface) and low elsewhere (`floor_mass` of the samples
   spread over [near, far]; uniform if the ray meets nothing).
4. Point feature f = Cat(e_g, e_h, e_p) + our additions: e_g trilinearly interpolated encoder features;
   e_h = E_h^T h with h the normalized 64-bin histogram of the resampled points along the ray and E_h
   (64 x 16) learnable; e_p = (d, o x d) Plücker; added: Fourier code of s / far and sub-voxel cues
   (class groups of the voxel holding the point and the point's position inside it), which the coarse
   encoder cannot provide.
5. SDF MLP -> f(s) and a feature u; beta_i = max((Phi(f_i) - Phi(f_{i+1})) / Phi(f_i), 0), Phi the
   sigmoid with learnable sharpness; w_i = prod_{j<i} (1 - beta_j) beta_i over the intervals between
   consecutive samples; depth h = sum w_i m_i (m_i the interval midpoints); v_r = sum w_i u_i, with the
   opacity sum w_i and e_h -> MLP -> intensity (sigmoid) and ray-drop logit.
Loss: L1 depth (returned rays) + l1 * L1 intensity + l2 * BCE drop + l3 * ray smoothness
|d_{j+1} - d_j| * exp(-||h_{j+1} - h_j||_1) over azimuth-consecutive rays (rays come in patches of
`patch` consecutive azimuth steps of one beam) + l4 * free space -log Phi(f) on the samples in front of
the first occupied march point (all samples of a ray that meets nothing), so that empty rays render no
surface. Generation: a ray returns if its opacity is >= 1/2 and a Bernoulli draw with the predicted
drop probability keeps it.

Training targets: the dataset holds occupancy only, so the "real" sweeps are the ray-casting sensor with
`SensorEffects` (noise, drop-out, mounting error); the model is given the nominal rig.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nuplan_occ.dataset import open_dataset
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import LIDAR_NAMES, PointCloud
from occgen.lidar_sampling import GROUPS, N_GROUPS, occupancy_prior_samples, point_cues
from occgen.lidar_raycast import (LidarSpec, RangeImage, SensorEffects, VoxelRaycaster, default_lidar_rig, scan,
                                  to_point_cloud)
from occgen.video_cond import load_local_state

N_LIDARS = len(LIDAR_NAMES)


@dataclass
class LidarModelConfig:
    """Sizes and loss weights; lengths in metres."""

    pool: int = 4
    channels: int = 16
    blocks: int = 2
    rig_dim: int = 32
    freqs: int = 4
    n_samples: int = 32
    march_step: float = 0.125
    window_before: int = 2
    window_after: int = 2
    floor_mass: float = 0.25
    hist_bins: int = 64
    hist_dim: int = 16
    hidden: int = 64
    feat_dim: int = 16
    near: float = 1.0
    far: float = 80.0
    patch: int = 8
    lambda_intensity: float = 1.0
    lambda_drop: float = 0.5
    lambda_smooth: float = 0.1
    lambda_free: float = 0.3
    init_sharpness: float = 20.0


def encoder_input(semantics: np.ndarray, pool: int) -> torch.Tensor:
    """(1, 5, X/pool, Y/pool, Z/pool) float32 class-group fractions (lidar_sampling.GROUPS order)."""
    s = np.asarray(semantics)
    X, Y, Z = (n // pool for n in s.shape)
    s = s[: X * pool, : Y * pool, : Z * pool]
    member = GROUPS.bool().numpy()
    stack = np.stack([member[:, g][s] for g in range(N_GROUPS)]).astype(np.float32)
    pooled = stack.reshape(N_GROUPS, X, pool, Y, pool, Z, pool).mean(axis=(2, 4, 6))
    return torch.from_numpy(pooled)[None]


def fourier(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """(..., D) -> (..., D * (1 + 2 freqs)): x, sin(2^k pi x), cos(2^k pi x)."""
    scaled = x[..., None] * (math.pi * 2.0 ** torch.arange(freqs, dtype=x.dtype))
    return torch.cat([x, scaled.sin().flatten(-2), scaled.cos().flatten(-2)], dim=-1)


class AdaLNZeroBlock(nn.Module):
    """X + gate * (norm(Conv3D(X)) * (1 + scale) + shift), (scale, shift, gate) = zero-init Linear(f_r)."""

    def __init__(self, channels: int, rig_dim: int):
        super().__init__()
        self.conv = nn.Conv3d(channels, channels, 3, padding=1)
        self.norm = nn.GroupNorm(4, channels, affine=False)
        self.ada = nn.Linear(rig_dim, 3 * channels)
        nn.init.zeros_(self.ada.weight)
        nn.init.zeros_(self.ada.bias)

    def forward(self, x: torch.Tensor, f_r: torch.Tensor) -> torch.Tensor:
        scale, shift, gate = (t[:, :, None, None, None] for t in self.ada(f_r).chunk(3, dim=-1))
        return x + gate * F.silu(self.norm(self.conv(x)) * (1.0 + scale) + shift)


class LidarModel(nn.Module):
    """See the module docstring. `forward` renders rays; `loss` adds the training objective."""

    def __init__(self, cfg: LidarModelConfig = LidarModelConfig()):
        super().__init__()
        self.cfg = cfg
        c = cfg.channels
        self.stem = nn.Conv3d(N_GROUPS, c, 3, stride=2, padding=1)
        self.blocks = nn.ModuleList(AdaLNZeroBlock(c, cfg.rig_dim) for _ in range(cfg.blocks))
        slot = 3 * (1 + 2 * cfg.freqs)
        self.rig_net = nn.Sequential(nn.Linear(N_LIDARS * slot, cfg.rig_dim), nn.SiLU(), nn.Linear(cfg.rig_dim, cfg.rig_dim))
        self.hist_embed = nn.Parameter(0.1 * torch.randn(cfg.hist_bins, cfg.hist_dim))
        point_in = c + cfg.hist_dim + 6 + (1 + 2 * cfg.freqs) + N_GROUPS + 3
        self.sdf = nn.Sequential(nn.Linear(point_in, cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, cfg.hidden), nn.SiLU(),
                                 nn.Linear(cfg.hidden, 1 + cfg.feat_dim))
        self.head = nn.Sequential(nn.Linear(cfg.feat_dim + 1 + cfg.hist_dim, cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, 2))
        self.log_sharpness = nn.Parameter(torch.tensor(math.log(cfg.init_sharpness)))

    # ---------------------------------------------------------------- conditioning
    def rig_embedding(self, origins: torch.Tensor, selected: torch.Tensor) -> torch.Tensor:
        """origins (5, 3) m ego frame, selected (5,) bool -> f_r (1, rig_dim)."""
        codes = fourier(origins / 5.0, self.cfg.freqs) * selected[:, None].float()
        return self.rig_net(codes.reshape(1, -1))

    def encode(self, occ_input: torch.Tensor, f_r: torch.Tensor) -> torch.Tensor:
        """(1, 5, X', Y', Z') class fractions -> (1, C, X'/2, Y'/2, Z'/2) features."""
        x = self.stem(occ_input)
        for block in self.blocks:
            x = block(x, f_r)
        return x

    # ---------------------------------------------------------------- rays
    def sample_rays(self, labels: torch.Tensor, grid: GridSpec, o: torch.Tensor, d: torch.Tensor, jitter: bool
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Occupancy-prior samples of rays o, d (R, 3) against the label grid: s (R, n) sorted m, the
        normalized histogram (R, bins) of s over [near, far] and the free-space depth (R,) m."""
        cfg = self.cfg
        s, free_depth = occupancy_prior_samples(labels, grid, o, d, cfg.n_samples, cfg.near, cfg.far, cfg.march_step,
                                    cfg.window_before, cfg.window_after, cfg.floor_mass, jitter)
        b = torch.clamp(((s - cfg.near) / (cfg.far - cfg.near) * cfg.hist_bins).long(), 0, cfg.hist_bins - 1)
        hist = torch.zeros(len(o), cfg.hist_bins).scatter_add_(1, b, torch.ones_like(s)) / cfg.n_samples
        return s, hist, free_depth

    def forward(self, feats: torch.Tensor, labels: torch.Tensor, grid: GridSpec, o: torch.Tensor, d: torch.Tensor,
                jitter: bool = False) -> dict[str, torch.Tensor]:
        """Render rays o, d (R, 3) (ego frame) against encoder features `feats` of the label grid `labels`."""
        cfg = self.cfg
        with torch.no_grad():
            s, hist, free_depth = self.sample_rays(labels, grid, o, d, jitter)
            pts = o[:, None] + s[..., None] * d[:, None]  # (R, n, 3)
            cues = point_cues(labels, grid, pts)
        lower = torch.as_tensor(grid.lower, dtype=torch.float32)
        upper = torch.as_tensor(grid.upper, dtype=torch.float32)
        norm = (pts - lower) / (upper - lower) * 2.0 - 1.0
        e_g = F.grid_sample(feats, norm.flip(-1).reshape(1, 1, 1, -1, 3), align_corners=False)
        e_g = e_g.reshape(feats.shape[1], *s.shape).permute(1, 2, 0)  # (R, n, C)
        e_h = (hist @ self.hist_embed)[:, None].expand(-1, s.shape[1], -1)
        e_p = torch.cat([d, torch.cross(o, d, dim=-1)], dim=-1)[:, None].expand(-1, s.shape[1], -1)
        extra = torch.cat([fourier((s / cfg.far)[..., None], cfg.freqs), cues], dim=-1)
        out = self.sdf(torch.cat([e_g, e_h, e_p, extra], dim=-1))
        sdf, u = out[..., 0], out[..., 1:]
        phi = torch.sigmoid(torch.exp(self.log_sharpness) * sdf)
        beta = torch.clamp((phi[:, :-1] - phi[:, 1:]) / (phi[:, :-1] + 1e-6), 0.0, 1.0)
        trans = torch.cumprod(torch.cat([torch.ones_like(beta[:, :1]), 1.0 - beta[:, :-1]], dim=1), dim=1)
        w = trans * beta  # (R, n - 1), one weight per interval between consecutive samples
        depth = (w * 0.5 * (s[:, :-1] + s[:, 1:])).sum(1)
        v_r = (w[..., None] * 0.5 * (u[:, :-1] + u[:, 1:])).sum(1)
        head = self.head(torch.cat([v_r, w.sum(1, keepdim=True), e_h[:, 0]], dim=-1))
        return {"depth": depth, "weight": w.sum(1), "intensity": torch.sigmoid(head[:, 0]),
                "drop_logit": head[:, 1], "hist": hist, "free_phi": phi[s < free_depth[:, None]]}

    def loss(self, pred: dict[str, torch.Tensor], target_range: torch.Tensor, target_intensity: torch.Tensor
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """Training loss; targets (R,) with NaN range for dropped rays; rays in patches of cfg.patch."""
        cfg = self.cfg
        hit = torch.isfinite(target_range)
        zero = pred["depth"].sum() * 0.0
        l_depth = (pred["depth"][hit] - target_range[hit]).abs().mean() if hit.any() else zero
        l_int = (pred["intensity"][hit] - target_intensity[hit]).abs().mean() if hit.any() else zero
        l_drop = F.binary_cross_entropy_with_logits(pred["drop_logit"], (~hit).float())
        dd = pred["depth"].reshape(-1, cfg.patch)
        hh = pred["hist"].reshape(-1, cfg.patch, cfg.hist_bins)
        l_smooth = ((dd[:, 1:] - dd[:, :-1]).abs() * torch.exp(-(hh[:, 1:] - hh[:, :-1]).abs().sum(-1))).mean()
        l_free = -torch.log(pred["free_phi"] + 1e-6).mean() if pred["free_phi"].numel() else zero
        total = (l_depth + cfg.lambda_intensity * l_int + cfg.lambda_drop * l_drop + cfg.lambda_smooth * l_smooth
                 + cfg.lambda_free * l_free)
        parts = {k: float(v.detach()) for k, v in
                 (("depth", l_depth), ("intensity", l_int), ("drop", l_drop), ("smooth", l_smooth), ("free", l_free))}
        return total, parts


@dataclass
class TrainFrame:
    """One training frame: encoder input, the label grid (X, Y, Z) uint8 and the target range images."""

    occ_input: torch.Tensor
    labels: torch.Tensor
    targets: list[RangeImage]


def make_frame(semantics: np.ndarray, grid: GridSpec, rig: list[LidarSpec], cfg: LidarModelConfig,
               effects: SensorEffects | None) -> TrainFrame:
    """Targets of a grid from the ray-casting sensor (with `effects`, the stand-in real sensor)."""
    caster = VoxelRaycaster(semantics, grid)
    return TrainFrame(encoder_input(semantics, cfg.pool), torch.from_numpy(np.asarray(semantics, dtype=np.uint8)),
                      [scan(caster, spec, effects) for spec in rig])


def _rig_tensors(rig: list[LidarSpec]) -> torch.Tensor:
    origins = torch.zeros(N_LIDARS, 3)
    for spec in rig:
        origins[spec.lidar_info] = torch.tensor(spec.position_ego, dtype=torch.float32)
    return origins


def _batch(frame: TrainFrame, rig: list[LidarSpec], chosen: list[int], n_patches: int, patch: int,
           rng: np.random.Generator):
    """Rays (nominal rig) and targets of `n_patches` runs of `patch` consecutive azimuths."""
    o, d, tr, ti = [], [], [], []
    for k in rng.choice(chosen, size=n_patches):
        spec, img = rig[k], frame.targets[k]
        origin, dirs = spec.rays()
        beam = rng.integers(spec.shape[0])
        a0 = rng.integers(spec.shape[1] - patch + 1)
        sl = (beam, slice(a0, a0 + patch))
        o.append(np.broadcast_to(origin, (patch, 3)))
        d.append(dirs[sl])
        tr.append(img.range[sl])
        ti.append(img.intensity[sl])
    as_t = lambda parts: torch.from_numpy(np.concatenate(parts).astype(np.float32))  # noqa: E731
    return as_t(o), as_t(d), as_t(tr), as_t(ti)


def train(model: LidarModel, frames: list[TrainFrame], grid: GridSpec, rig: list[LidarSpec], steps: int,
          n_patches: int = 96, lr: float = 3e-3, seed: int = 0) -> list[float]:
    """Adam steps (cosine learning-rate decay to lr / 20) on random frames and random LiDAR subsets;
    returns the loss of every step."""
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, steps), eta_min=lr / 20.0)
    origins = _rig_tensors(rig)
    losses = []
    for _ in range(steps):
        frame = frames[rng.integers(len(frames))]
        chosen = sorted(rng.choice(len(rig), size=rng.integers(1, len(rig) + 1), replace=False).tolist())
        selected = torch.zeros(N_LIDARS, dtype=torch.bool)
        selected[[rig[k].lidar_info for k in chosen]] = True
        o, d, tr, ti = _batch(frame, rig, chosen, n_patches, model.cfg.patch, rng)
        feats = model.encode(frame.occ_input, model.rig_embedding(origins, selected))
        loss, _ = model.loss(model(feats, frame.labels, grid, o, d, jitter=True), tr, ti)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    return losses


@torch.no_grad()
def generate(model: LidarModel, semantics: np.ndarray, grid: GridSpec = DEFAULT_GRID,
             rig: list[LidarSpec] | None = None, seed: int = 0, chunk: int = 4096) -> PointCloud:
    """A sweep of every LiDAR of `rig` (default rig) for one grid; frame "lidar" = ego. A ray returns
    if its rendered opacity (sum of the weights) is at least 1/2, it is not dropped (probability
    sigmoid(drop logit), Bernoulli draws from `seed`) and its depth is inside [min_range, max_range]."""
    rig = rig or default_lidar_rig()
    selected = torch.zeros(N_LIDARS, dtype=torch.bool)
    selected[[s.lidar_info for s in rig]] = True
    feats = model.encode(encoder_input(semantics, model.cfg.pool), model.rig_embedding(_rig_tensors(rig), selected))
    labels = torch.from_numpy(np.asarray(semantics, dtype=np.uint8))
    gen = torch.Generator().manual_seed(seed)
    images = []
    for spec in rig:
        origin, dirs = spec.rays()
        flat = torch.from_numpy(dirs.reshape(-1, 3).astype(np.float32))
        o = torch.from_numpy(origin.astype(np.float32)).expand(chunk, 3)
        rng_, inten = [], []
        for i in range(0, len(flat), chunk):
            d = flat[i:i + chunk]
            pred = model(feats, labels, grid, o[: len(d)], d)
            returned = torch.rand(len(d), generator=gen) >= torch.sigmoid(pred["drop_logit"])
            keep = returned & (pred["weight"] >= 0.5) & (pred["depth"] >= spec.min_range) & (pred["depth"] <= spec.max_range)
            rng_.append(torch.where(keep, pred["depth"], torch.nan))
            inten.append(pred["intensity"])
        images.append(RangeImage(spec, origin, dirs, torch.cat(rng_).numpy().reshape(spec.shape).astype(np.float64),
                                 torch.cat(inten).numpy().reshape(spec.shape), np.zeros(spec.shape, np.uint8)))
    return to_point_cloud(images)


def save_checkpoint(model: LidarModel, path: str | Path) -> None:
    """Config and weights as plain tensors/dicts (loadable with weights_only=True)."""
    torch.save({"config": asdict(model.cfg), "state": model.state_dict()}, str(path))


def load_checkpoint(path: str | Path) -> LidarModel:
    """A model from a local checkpoint written by `save_checkpoint` (no download, weights_only)."""
    blob = load_local_state(path)
    model = LidarModel(LidarModelConfig(**blob["config"]))
    model.load_state_dict(blob["state"])
    return model


def dataset_frames(root: str, indices: list[int], rig: list[LidarSpec], cfg: LidarModelConfig,
                   effects_seed: int | None = 0) -> tuple[GridSpec, list[str], list[np.ndarray], list[TrainFrame]]:
    """(grid, tokens, semantics, TrainFrames with stand-in real targets) of dataset frames."""
    ds = open_dataset(root)
    tokens, sems, frames = [], [], []
    for i in indices:
        f = ds.get(int(i), keys=["semantics"])
        effects = None if effects_seed is None else SensorEffects(seed=effects_seed + int(i))
        tokens.append(f["token"])
        sems.append(f["semantics"])
        frames.append(make_frame(f["semantics"], ds.grid, rig, cfg, effects))
    return ds.grid, tokens, sems, frames
