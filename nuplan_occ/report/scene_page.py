"""One scene's page of the report, written into its own folder: QA plots over time, the class histogram,
top-down thumbnails every N frames with the ego path, the flagged frames' thumbnails and the frame table.

The folder holds `key.txt` (the content key it was rendered for) and `gallery.json` (its flagged frames for
the report's gallery), so an unchanged scene is not rendered again.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from nuplan_occ.rays.consistency import FLAG_RULES
from nuplan_occ.report import html as h
from nuplan_occ.report.flags import OBSERVED_FRACTION_OF_MEDIAN, POSE_CORRECTION_MAX_M, RULES, FlagResult
from nuplan_occ.report.frames import BuildFrames
from nuplan_occ.report.plots import Series, plot_class_histogram, plot_timeline
from nuplan_occ.report.scenes import SceneSummary
from nuplan_occ.report.topdown import draw_path, path_pixels, render_topdown

GALLERY_PER_SCENE = 6
"""Flagged ok frames of a scene that get a thumbnail in the gallery (the first ones in time)."""

KEY_FILE, GALLERY_FILE = "key.txt", "gallery.json"
RULE_TITLES = {r.name: r.title for r in RULES}


@dataclass
class GalleryItem:
    """A flagged frame: its scene, identity, rules it broke, failure reason, and its thumbnail relative to
    the report root ("" for a failed frame, which has no grid)."""

    page_id: str
    scene: str
    frame_index: int
    token: str
    rules: list[str]
    reason: str
    image: str


@dataclass(frozen=True)
class PageContext:
    """What every scene page shares: the dataset root (for commands), thumbnail stride, palette (256, 3),
    class names and colours, the build's median observed fraction."""

    root: str
    every: int
    palette: np.ndarray
    names: dict[int, str]
    colors: dict[int, tuple[int, int, int]]
    observed_median: float


def is_current(folder: Path, key: str) -> bool:
    """True when the folder holds a complete page rendered for this key."""
    return (folder / KEY_FILE).exists() and (folder / KEY_FILE).read_text() == key and (folder / GALLERY_FILE).exists()


def read_gallery(folder: Path) -> list[GalleryItem]:
    return [GalleryItem(**item) for item in json.loads((folder / GALLERY_FILE).read_text())]


def _thumbnail(ds, token: str, poses: np.ndarray, pose: np.ndarray, ctx: PageContext, path: Path) -> None:
    semantics = ds.get(ds.index_of_token(token), keys=("semantics",))["semantics"]
    image = draw_path(render_topdown(semantics, ctx.palette), path_pixels(poses, pose, ds.grid))
    plt.imsave(path, image)


def _frame_rules(flags: FlagResult, row: int) -> list[str]:
    return [name for name, mask in flags.masks.items() if mask[row]]


def _badges(rules: list[str]) -> str:
    return "".join(f'<span class="badge {h.esc(r)}" title="{h.esc(RULE_TITLES[r])}">{h.esc(r)}</span>' for r in rules)


def _legend(ctx: PageContext) -> str:
    items = "".join(f'<span><i style="background:rgb{tuple(ctx.colors[i])}"></i>{h.esc(n)}</span>'
                    for i, n in sorted(ctx.names.items()) if i > 0)
    return (f'<div class="legend">{items}<span><i style="background:rgb(255,40,200)"></i>ego path</span>'
            '<span><i style="background:#fff"></i>ego</span></div>')


def render_scene(scene: SceneSummary, frames: BuildFrames, flags: FlagResult, ds, ctx: PageContext,
                 folder: Path, key: str) -> list[GalleryItem]:
    """Write the scene's page and pictures into `folder` (relative links: the report root is ../..);
    returns its gallery items."""
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.png"):
        old.unlink()
    rows = np.arange(scene.start, scene.stop)
    c = frames.columns
    ok = frames.ok[rows]
    poses = frames.poses[rows]
    seconds = (c["timestamp_us"][rows] - c["timestamp_us"][scene.start]) * 1e-6
    flagged = flags.flagged[rows]

    def col(name: str) -> np.ndarray:
        return np.where(ok, c[name][rows], np.nan) if name in c else np.full(len(rows), np.nan)

    plot_timeline(seconds, [
        Series("pose correction (m)", col("qa_pose_correction_m"), (POSE_CORRECTION_MAX_M, "flag")),
        Series("map offset (m)", col("qa_map_offset_m")),
        Series("LiDAR observed\nfraction", col("qa_lidar_observed_fraction"),
               (OBSERVED_FRACTION_OF_MEDIAN * ctx.observed_median, "flag")),
        Series("occupied voxels", col("qa_occupied_voxels")),
        Series("rays agreeing\n(share)", col("qa_ray_agree"), (FLAG_RULES["rays_disagree"][2], "flag")),
        Series("rays ending\nearly (share)", col("qa_ray_early"), (FLAG_RULES["rays_early"][2], "flag")),
    ], ~ok, flagged, folder / "timeline.png")
    plot_class_histogram(frames.class_hist[rows][ok].sum(axis=0) if ok.any() else np.zeros(1, np.int64),
                         ctx.names, ctx.colors, folder / "classes.png")

    tokens = [str(t) for t in c["token"][rows]]
    ok_positions = np.flatnonzero(ok)
    thumbs = []
    for k in ok_positions[::max(1, ctx.every)]:
        name = f"top-{int(c['frame_index'][rows[k]]):06d}.png"
        _thumbnail(ds, tokens[k], poses, poses[k], ctx, folder / name)
        thumbs.append((k, name))
    gallery = []
    for k in np.flatnonzero(flagged):
        rules = _frame_rules(flags, rows[k])
        image = ""
        if ok[k] and sum(1 for g in gallery if g.image) < GALLERY_PER_SCENE:
            name = f"top-{int(c['frame_index'][rows[k]]):06d}.png"
            if not (folder / name).exists():
                _thumbnail(ds, tokens[k], poses, poses[k], ctx, folder / name)
            image = f"scenes/{scene.page_id}/{name}"
        gallery.append(GalleryItem(scene.page_id, scene.scene, int(c["frame_index"][rows[k]]), tokens[k], rules,
                                   str(c["failure_reason"][rows[k]]), image))

    (folder / "index.html").write_text(_page(scene, frames, flags, ctx, rows, seconds, thumbs, tokens))
    (folder / GALLERY_FILE).write_text(json.dumps([asdict(g) for g in gallery]))
    (folder / KEY_FILE).write_text(key)
    return gallery


def _page(scene: SceneSummary, frames: BuildFrames, flags: FlagResult, ctx: PageContext, rows: np.ndarray,
          seconds: np.ndarray, thumbs: list[tuple[int, str]], tokens: list[str]) -> str:
    c = frames.columns
    thumb_html = "".join(
        f'<figure><a href="{name}"><img src="{name}" alt="frame {int(c["frame_index"][rows[k]])}"></a>'
        f'<figcaption>t = {seconds[k]:.1f} s, frame {int(c["frame_index"][rows[k]])}<br>'
        f'<a href="#f-{h.esc(tokens[k])}" class="mono">{h.esc(tokens[k])}</a> {_badges(_frame_rules(flags, rows[k]))}'
        "</figcaption></figure>" for k, name in thumbs)

    def value(name: str, row: int, digits: int = 3) -> h.Cell:
        return h.num(float(c[name][row]) if name in c else None, digits)

    table_rows = []
    for k, row in enumerate(rows):
        rules = _frame_rules(flags, row)
        css = "failed" if not frames.ok[row] else ("flagged" if rules else "")
        status = "ok" if frames.ok[row] else f"failed: {c['failure_reason'][row]}"
        table_rows.append((css, [
            h.Cell(f'<span id="f-{h.esc(tokens[k])}">{int(c["frame_index"][row])}</span>', float(c["frame_index"][row])),
            h.num(float(seconds[k]), 3), h.Cell(f'<span class="mono">{h.esc(tokens[k])}</span>'),
            h.text(status), h.Cell(_badges(rules)), value("qa_pose_correction_m", row),
            value("qa_map_offset_m", row), value("qa_lidar_observed_fraction", row), value("qa_point_coverage", row),
            value("qa_occupied_voxels", row), value("qa_boxes_with_points", row), value("qa_boxes_labeled", row),
            h.num(float(c["nbytes"][row]) / 1024 if frames.ok[row] else None, 3)]))
    frame_table = h.table(["frame", "t (s)", "token", "status", "flags", "pose corr. (m)", "map offset (m)",
                           "observed frac.", "point coverage", "occupied voxels", "boxes w/ points", "boxes labeled",
                           "KiB"], table_rows)
    timing = ", ".join(f"{k} {v:.1f} s" for k, v in scene.stage_seconds.items()) or "not recorded (no build log)"
    flagged = ", ".join(f"{n}: {v}" for n, v in scene.flag_counts.items() if v) or "none"
    body = (
        f'<div class="cards"><div class="card"><div class="v">{scene.frames}</div><div class="k">frames</div></div>'
        f'<div class="card{" bad" if scene.failed else ""}"><div class="v">{scene.failed}</div><div class="k">failed</div></div>'
        f'<div class="card{" bad" if scene.flagged else ""}"><div class="v">{scene.flagged}</div><div class="k">flagged</div></div>'
        f'<div class="card"><div class="v">{h.fmt(scene.seconds_per_frame)}</div><div class="k">build s / frame</div></div>'
        f'<div class="card"><div class="v">{h.fmt(scene.kib_per_frame)}</div><div class="k">KiB / frame</div></div></div>'
        f'<p>Flagged frames by rule: {h.esc(flagged)}. Stage times: {h.esc(timing)}.</p>'
        f'<p class="muted">Open a frame in 3D: <span class="mono">nuplan-occ view {h.esc(ctx.root)} --token TOKEN</span></p>'
        '<div class="row"><div><h2>QA over time</h2><img class="plot" src="timeline.png" alt="QA figures over time">'
        '</div><div><h2>Classes</h2><img class="plot" src="classes.png" alt="class histogram"></div></div>'
        f'<h2>Top-down, every {ctx.every} frames</h2><p class="muted">Up is forward (+x), left is left (+y), '
        '100 m x 100 m, one pixel per 0.25 m column: the top voxel\'s class, darker when lower.</p>'
        f'{_legend(ctx)}<div class="thumbs">{thumb_html or "<p>no ok frame</p>"}</div>'
        f'<h2>Frames</h2>{frame_table}')
    return h.page(f"{scene.log} / {scene.scene}", f"scene token {h.esc(scene.scene_token)}",
                  [("report", "../../index.html"), ("scenes", "../../scenes-001.html"), ("gallery", "../../gallery-001.html")],
                  body)
