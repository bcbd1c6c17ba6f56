"""`write_report(root, out)`: the static HTML report of a built dataset (opens from disk, no external resource).

    out/index.html               build summary, failure reasons grouped, the flag rules and their counts,
                                 the most flagged scenes, params and versions
    out/scenes-NNN.html          the scene table, SCENES_PER_PAGE scenes a page (sortable by each figure)
    out/gallery-NNN.html         the flagged frames, GALLERY_PER_PAGE a page
    out/scenes/<log>--<scene>/   one folder per scene: its page and pictures (see scene_page.py)

Incremental: a scene's page is keyed by its manifest rows, its flags, its build times and the report's own
code; a rerun renders only the scenes whose key changed (and removes the folders of scenes no longer in the
dataset). The index, table and gallery pages are text and rewritten every run.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from nuplan_occ.dataset import open_dataset
from nuplan_occ.pipeline.build import default_work_root
from nuplan_occ.pipeline.build_log import latest_versions, read_build_log, scene_seconds
from nuplan_occ.report import html as h
from nuplan_occ.report.flags import RULES, build_median, evaluate_rules
from nuplan_occ.report.frames import load_frames
from nuplan_occ.report.scene_page import GALLERY_PER_SCENE, GalleryItem, PageContext, is_current, read_gallery, render_scene
from nuplan_occ.report.scenes import FIGURES, SceneSummary, summarize_scenes
from nuplan_occ.storage import read_metadata

SCENES_PER_PAGE = 100
GALLERY_PER_PAGE = 60
TOP_SCENES = 15
"""Scenes of the index page's 'most flagged' table."""


@dataclass
class ReportResult:
    """index: the report's index.html; rendered / reused: scene pages drawn this run / kept from an earlier one;
    flagged_frames: frames any rule flags; rule_frames: rule name -> frames it flags (evaluated rules only)."""

    index: Path
    scenes: int
    rendered: int
    reused: int
    flagged_frames: int
    rule_frames: dict[str, int]


def reason_group(reason: str) -> str:
    """A failure reason without the file it names and with numbers as N, so equal problems group together."""
    first = reason.splitlines()[0] if reason else "unknown"
    first = re.sub(r"^\S*[/\\]\S*?: ", "", first)
    return re.sub(r"\d+", "N", first)


def _code_key() -> str:
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _rule_disabled(metadata: dict) -> dict[str, str]:
    label = metadata.get("params", {}).get("label", {})
    if label.get("align_to_paint") is False:
        return {"map_refused": "map alignment switched off by the build's params (label.align_to_paint = false)"}
    return {}


def write_report(root: str, out: Path | None = None, *, every: int = 10, work_root: Path | None = None,
                 progress: Callable[[int, int, str], None] | None = None) -> ReportResult:
    """Write (or update) the report of the dataset at `root` into `out` (default ROOT/report, local roots
    only). every: a thumbnail every N ok frames of a scene. work_root: where the build log is (default the
    build's default work folder). progress(done, total, scene) is called per scene."""
    out = Path(out) if out is not None else Path(root.removeprefix("file://")) / "report"
    out.mkdir(parents=True, exist_ok=True)
    metadata = read_metadata(root)
    labels = {int(c["id"]): c for c in metadata["labels"]["classes"]}
    frames = load_frames(root)
    log = read_build_log(Path(work_root) if work_root else default_work_root(root))
    flags = evaluate_rules(frames.columns, frames.ok, disabled=_rule_disabled(metadata))
    scenes = summarize_scenes(frames, flags, scene_seconds(log))
    observed = frames.columns.get("qa_lidar_observed_fraction")
    ctx = PageContext(root=root, every=every, palette=_palette(labels),
                      names={i: v["name"] for i, v in labels.items()},
                      colors={i: tuple(v["color"]) for i, v in labels.items()},
                      observed_median=build_median(observed, frames.ok) if observed is not None else float("nan"))
    code = _code_key()
    gallery: list[GalleryItem] = []
    rendered = 0
    ds = None  # opened when the first scene needs its grids
    for done, scene in enumerate(scenes):
        folder = out / "scenes" / scene.page_id
        key = _scene_key(frames.scene_key(scene.start, scene.stop), flags, scene, ctx, code)
        if is_current(folder, key):
            gallery += read_gallery(folder)
        else:
            ds = ds or open_dataset(root)
            gallery += render_scene(scene, frames, flags, ds, ctx, folder, key)
            rendered += 1
        if progress:
            progress(done + 1, len(scenes), f"{scene.log} / {scene.scene}")
    _remove_stale(out / "scenes", {s.page_id for s in scenes})
    if ds is not None:
        ds.close()
    _write_scene_tables(out, scenes, flags)
    _write_gallery(out, gallery)
    index = out / "index.html"
    index.write_text(_index_page(root, metadata, frames, flags, scenes, log, len(gallery)))
    return ReportResult(index, len(scenes), rendered, len(scenes) - rendered, len(gallery),
                        {name: int(mask.sum()) for name, mask in flags.masks.items()})


def _palette(labels: dict) -> np.ndarray:
    lut = np.zeros((256, 3), dtype=np.uint8)
    for i, v in labels.items():
        lut[i] = v["color"]
    return lut


def _scene_key(rows_key: str, flags, scene: SceneSummary, ctx: PageContext, code: str) -> str:
    rows = slice(scene.start, scene.stop)
    digest = hashlib.sha256(f"{rows_key}|{code}|{ctx.every}|{ctx.root}|{ctx.observed_median!r}".encode())
    for name in sorted(flags.masks):
        digest.update(name.encode() + np.packbits(flags.masks[name][rows]).tobytes())
    digest.update(json.dumps(scene.stage_seconds, sort_keys=True).encode())
    return digest.hexdigest()


def _remove_stale(folder: Path, keep: set[str]) -> None:
    if folder.exists():
        for path in folder.iterdir():
            if path.is_dir() and path.name not in keep:
                shutil.rmtree(path)


def _scene_row(s: SceneSummary, rules: list[str]) -> tuple[str, list[h.Cell]]:
    badges = "".join(f'<span class="badge {r}">{r} {s.flag_counts[r]}</span>' for r in rules if s.flag_counts.get(r))
    css = "failed" if s.failed else ("flagged" if s.flagged else "")
    return css, [h.text(s.log), h.Cell(f'<a href="{h.esc(s.href)}">{h.esc(s.scene)}</a>'), h.num(s.frames),
                 h.num(s.failed), h.num(s.flagged), h.Cell(badges, float(s.flagged)),
                 *[h.num(s.figures[f.key]) for f in FIGURES], h.num(s.seconds_per_frame), h.num(s.kib_per_frame)]


SCENE_HEADERS = ["log", "scene", "frames", "failed", "flagged", "flags", *[f.header for f in FIGURES],
                 "build s/frame", "KiB/frame"]


def _ranked(scenes: list[SceneSummary]) -> list[SceneSummary]:
    """Most flagged first (failed frames first among equals), then log and scene order."""
    return sorted(scenes, key=lambda s: (-s.flagged, -s.failed, s.log, s.scene))


def _nav(prefix: str = "") -> list[tuple[str, str]]:
    return [("report", f"{prefix}index.html"), ("scenes", f"{prefix}scenes-001.html"),
            ("gallery", f"{prefix}gallery-001.html")]


def _write_paged(out: Path, stem: str, title: str, intro: str, items: list, per_page: int,
                 render: Callable[[list], str]) -> None:
    """Pages `<stem>-NNN.html` of `items`, per_page a page (one page when empty), each the intro, a pager and
    render(the page's items); removes pages left over from a larger report."""
    pages = max(1, -(-len(items) // per_page))
    for k in range(1, pages + 1):
        pager = h.pager(k, pages, lambda j: f"{stem}-{j:03d}.html")
        body = f"{intro}{pager}{render(items[(k - 1) * per_page:k * per_page])}{pager}"
        (out / f"{stem}-{k:03d}.html").write_text(h.page(f"{title} (page {k} of {pages})", "", _nav(), body))
    for old in out.glob(f"{stem}-*.html"):
        if int(old.stem.rsplit("-", 1)[1]) > pages:
            old.unlink()


def _write_scene_tables(out: Path, scenes: list[SceneSummary], flags) -> None:
    rules = [r.name for r in RULES if r.name in flags.masks]
    intro = (f"<p>{len(scenes)} scenes, most flagged first; click a header to sort this page. Rules: see the "
             '<a href="index.html#rules">report</a>.</p>')
    _write_paged(out, "scenes", "Scenes", intro, _ranked(scenes), SCENES_PER_PAGE,
                 lambda chunk: h.table(SCENE_HEADERS, [_scene_row(s, rules) for s in chunk]))


def _gallery_card(g: GalleryItem) -> str:
    badges = "".join(f'<span class="badge {h.esc(r)}">{h.esc(r)}</span>' for r in g.rules)
    link = f"scenes/{g.page_id}/index.html#f-{h.esc(g.token)}"
    if g.image:
        picture = f'<a href="{h.esc(link)}"><img src="{h.esc(g.image)}" alt="frame {g.frame_index}"></a>'
    else:
        note = f"failed, no grid: {h.esc(g.reason)}" if g.reason else "thumbnail limit of the scene reached: see its page"
        picture = f'<div class="nogrid">{note}</div>'
    return (f'<figure>{picture}<figcaption>{badges}<br><a href="{h.esc(link)}">{h.esc(g.scene)} frame '
            f'{g.frame_index}</a><br><span class="mono">{h.esc(g.token)}</span></figcaption></figure>')


def _write_gallery(out: Path, gallery: list[GalleryItem]) -> None:
    intro = (f"<p>{len(gallery)} flagged frames (failed frames have no grid; at most {GALLERY_PER_SCENE} thumbnails "
             "a scene, its page lists every frame).</p>")
    _write_paged(out, "gallery", "Flagged frames", intro, gallery, GALLERY_PER_PAGE,
                 lambda chunk: f'<div class="thumbs">{"".join(_gallery_card(g) for g in chunk)}</div>')


def _index_page(root: str, metadata: dict, frames, flags, scenes: list[SceneSummary], log: list[dict],
                gallery_size: int) -> str:
    ok = frames.ok
    n_ok, n_failed = int(ok.sum()), int((~ok).sum())
    nbytes = frames.columns["nbytes"][ok]
    timed = [s for s in scenes if s.stage_seconds]
    timed_frames = sum(s.frames for s in timed)
    stage_totals: Counter = Counter()
    for s in timed:
        stage_totals.update(s.stage_seconds)
    per_frame = sum(stage_totals.values()) / timed_frames if timed_frames else float("nan")

    def card(value: str, label: str, bad: bool = False) -> str:
        return f'<div class="card{" bad" if bad else ""}"><div class="v">{value}</div><div class="k">{label}</div></div>'

    cards = "".join([
        card(h.fmt(n_ok), "frames built"), card(h.fmt(n_failed), "frames failed", n_failed > 0),
        card(h.fmt(len(scenes)), "scenes"), card(h.fmt(len(set(frames.columns["log"].tolist()))), "logs"),
        card(h.fmt(int(flags.flagged.sum())), "flagged frames", bool(gallery_size)),
        card(h.fmt(float(nbytes.mean()) / 1024 if nbytes.size else None), "KiB / frame (stored)"),
        card(h.fmt(per_frame), "build s / frame (sum of stage times)")])

    failed_rows = np.flatnonzero(~ok)
    groups: dict[str, list[int]] = {}
    for row in failed_rows:
        groups.setdefault(reason_group(str(frames.columns["failure_reason"][row])), []).append(int(row))
    starts = np.array([s.start for s in scenes])

    def scene_of(row: int) -> SceneSummary:
        return scenes[int(np.searchsorted(starts, row, side="right")) - 1]

    reason_rows = [("", [h.text(group), h.num(len(rows)),
                         h.Cell(", ".join(f'<a href="{h.esc(scene_of(r).href)}#f-{h.esc(frames.columns["token"][r])}">'
                                          f"{h.esc(scene_of(r).scene)}</a>" for r in rows[:8])
                                + (f" and {len(rows) - 8} more" if len(rows) > 8 else "")),
                         h.Cell(f'<span class="mono">{h.esc(str(frames.columns["failure_reason"][rows[0]])[:300])}</span>')])
                   for group, rows in sorted(groups.items(), key=lambda kv: -len(kv[1]))]
    reasons = (h.table(["reason (file and numbers elided)", "frames", "frames (first 8)", "example"], reason_rows)
               if reason_rows else "<p>No frame failed.</p>")

    flagged_scenes = {r.name: sum(1 for s in scenes if s.flag_counts.get(r.name)) for r in RULES}
    rule_rows = []
    for r in RULES:
        if r.name in flags.masks:
            rule_rows.append(("flagged" if flags.masks[r.name].any() else "", [
                h.Cell(f'<span class="badge {r.name}">{r.name}</span>'), h.text(r.title),
                h.num(int(flags.masks[r.name].sum())), h.num(flagged_scenes[r.name])]))
        else:
            rule_rows.append(("", [h.Cell(f'<span class="badge off">{r.name}</span>'), h.text(r.title),
                                   h.Cell(f'<span class="muted">not evaluated: {h.esc(flags.skipped[r.name])}</span>'),
                                   h.text("")]))
    rules_html = h.table(["rule", "a frame is flagged when", "frames", "scenes"], rule_rows, sortable=False)

    top = _ranked(scenes)[:TOP_SCENES]
    rules = [r.name for r in RULES if r.name in flags.masks]
    top_html = h.table(SCENE_HEADERS, [_scene_row(s, rules) for s in top])

    stage_html = (h.table(["stage", "s (sum over scenes)", "s / frame"],
                          [("", [h.text(k), h.num(v), h.num(v / timed_frames)]) for k, v in stage_totals.items()])
                  if timed_frames else "<p class=\"muted\">No build log found beside the stage cache: times per frame "
                                       "are not recorded for this dataset.</p>")
    versions = {"format": metadata.get("format"), "schema_version": metadata.get("schema_version"),
                "software_version": metadata.get("software_version"), "software": metadata.get("software"),
                **{f"package {k}": v for k, v in latest_versions(log).items()}}
    versions_html = h.table(["what", "version"], [("", [h.text(k), h.text(v)]) for k, v in versions.items()
                                                  if v is not None], sortable=False)
    params = h.esc(json.dumps(metadata.get("params", {}), indent=2, sort_keys=True))
    body = (f'<div class="cards">{cards}</div>'
            f"<h2>Failure reasons</h2>{reasons}"
            f'<h2 id="rules">Flag rules</h2>{rules_html}'
            f'<h2>Most flagged scenes</h2><p>All {len(scenes)} scenes: <a href="scenes-001.html">scene table</a>; '
            f'{gallery_size} flagged frames: <a href="gallery-001.html">gallery</a>.</p>{top_html}'
            f"<h2>Build time</h2><p>Stage times from the build log (latest measured time of each stage of each scene; "
            f"{len(timed)} of {len(scenes)} scenes timed).</p>{stage_html}"
            f"<h2>Versions</h2>{versions_html}"
            f"<h2>Params</h2><details><summary>build params (dataset.json)</summary><pre>{params}</pre></details>")
    subtitle = f"{h.esc(root)} &middot; report written {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    return h.page("nuplan-occ build report", subtitle, _nav(), body)
