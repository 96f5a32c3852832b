"""``tpscore demo``: the whole expression-transfer pipeline on embedded procedural faces.

Writes, into the output folder: the three input scans as Bosphorus files (.bnt and
.lm3), then for each demonstrated expression the transferred target as .npz, OBJ and
PLY (with the u,v map), a picture of source, expression, target and result side by
side with an error heat map against the known ground truth, and an animated GIF of a
magnitude sweep. Then the physical skin: a fitted scan smiles, frowns and opens its
jaw (:func:`run_skin_demo`): the template head fitted to a procedural scan, its
skull, muscles and jaw carried along, and three expressions simulated.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from .. import datasets, render
from ..expression import transfer
from ..face import io
from ..face.grid import load_scan, resample_scan
from ..physics import SimulationOptions, SkinModel, fit_head

__all__ = ["run_demo", "run_skin_demo", "DEMO_EXPRESSIONS", "SKIN_DEMO_EXPRESSIONS"]

#: (file stem, AUs generated on the source, what is transferred)
DEMO_EXPRESSIONS = (
    ("au12", {"12": 1.0}, "12"),
    ("au4", {"4": 1.0}, "4"),
    ("sadness", {"1": 1.0, "4": 1.0, "15": 1.0}, "sadness"),
)


def _ground_truth(scan: datasets.SyntheticScan, expression: dict, points) -> np.ndarray:
    """True expressive positions of neutral target points (scan frame)."""
    pose = scan.pose
    inverse = np.linalg.inv(pose)
    face = points @ inverse[:3, :3].T + inverse[:3, 3]
    moved = face + datasets.au_displacement(scan.identity, expression, face[:, :2])
    return moved @ pose[:3, :3].T + pose[:3, 3]


def run_demo(out_dir="demo-output", *, quiet: bool = False) -> dict:
    """Run the demo and return a summary {stem: {"rms_mm": ..., "noop_rms_mm": ...}}."""
    out = Path(out_dir)
    (out / "scans").mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    def say(message):
        if not quiet:
            print(f"[{time.perf_counter() - start:6.2f} s] {message}", flush=True)

    summary = {}
    for stem, expression, request in DEMO_EXPRESSIONS:
        scans = datasets.demo_triplet(expression, noise_mm=0.1, holes=2, pose_deg=5.0, seed=7)
        names = ("source_neutral", "source_" + stem, "target_neutral")
        grids = []
        for name, scan in zip(names, scans):
            base = out / "scans" / name
            io.write_bnt(f"{base}.bnt", io.BntScan.from_points(scan.points, image_name=f"{name}.png"))
            io.write_lm3(f"{base}.lm3", scan.landmarks)
            grids.append(load_scan(f"{base}.bnt"))
        say(f"{stem}: wrote and re-read the source and target scans")

        result = transfer(*grids, request, 1.0)
        say(f"{stem}: transferred {'+'.join(result.animation.labels)}")

        mask = result.mask
        predicted = result.vertices[mask]
        neutral = result.neutral[mask]
        truth = _ground_truth(scans[2], expression, neutral)
        error = np.linalg.norm(predicted - truth, axis=1)
        moving = np.linalg.norm(truth - neutral, axis=1) > 0.5
        summary[stem] = dict(
            rms_mm=float(np.sqrt(np.mean(error[moving] ** 2))),
            noop_rms_mm=float(np.sqrt(np.mean(np.linalg.norm(truth - neutral, axis=1)[moving] ** 2))),
        )

        io.write_npz(out / f"target_{stem}.npz", **result.to_npz_dict())
        mesh = result.target.grid.with_points(result.vertices).mesh()
        for suffix in ("obj", "ply"):
            io.write_mesh(out / f"target_{stem}.{suffix}", mesh.vertices, mesh.faces, uv=mesh.uv)

        errors = np.full(mask.shape, np.nan)
        errors[mask] = error
        panels = [render.render_grid(g.points, g.mask) for g in grids]
        panels.append(render.render_grid(result.vertices, mask))
        heat_mesh = result.target.grid.with_points(result.vertices).mesh()
        panels.append(render.error_heatmap(heat_mesh.vertices, heat_mesh.faces,
                                           errors.reshape(-1)[heat_mesh.grid_index], vmax=2.0))
        titles = ["source neutral", f"source {stem}", "target neutral", f"target {stem} (transferred)",
                  "error vs truth (mm)"]
        render.save_png(out / f"transfer_{stem}.png", render.side_by_side(panels, titles))
        magnitudes = np.concatenate([np.linspace(0, 1, 10), np.linspace(1, 0, 10)[1:-1]])
        camera = render.fit_camera([result.vertices[mask]])
        frames = [render.render_grid(result.animation.frame_in_scan(m), mask, camera=camera)
                  for m in magnitudes]
        render.save_gif(out / f"sweep_{stem}.gif", frames, fps=12)
        say(f"{stem}: rms error {summary[stem]['rms_mm']:.2f} mm where the truth moves "
            f"(leaving the target neutral: {summary[stem]['noop_rms_mm']:.2f} mm); "
            f"wrote target_{stem}.npz/.obj/.ply, transfer_{stem}.png, sweep_{stem}.gif")
    summary["skin"] = run_skin_demo(out, quiet=quiet)
    say(f"done: outputs in {out.resolve()}")
    return summary


#: (file stem, title, AU intensities, jaw angle in degrees)
SKIN_DEMO_EXPRESSIONS = (
    ("smile", "smile (AU12)", {"12": 0.6}, 0.0),
    ("frown", "frown (AU4 + AU15)", {"4": 0.6, "15": 0.4}, 0.0),
    ("jaw", "jaw open 15 deg", {}, 15.0),
)
# The demo's subject: a procedural identity the template (the average face) is not.
_DEMO_IDENTITY_SEED = 202
_DEMO_SCAN_SEED = 9


def run_skin_demo(out_dir="demo-output", *, quiet: bool = False) -> dict:
    """Fit the template head to a procedural scan and animate three expressions.

    Writes ``skin_<stem>.png`` per expression and ``skin_expressions.gif`` into
    ``out_dir``; returns {stem: largest skin displacement (mm)}.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    def say(message):
        if not quiet:
            print(f"[{time.perf_counter() - start:6.2f} s] {message}", flush=True)

    scan = datasets.make_face(datasets.random_identity(_DEMO_IDENTITY_SEED), noise_mm=0.1, pose_deg=4.0,
                              seed=_DEMO_SCAN_SEED)
    grid = resample_scan(scan.points, scan.landmarks)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the procedural scan's coverage notes
        head, adaptation = fit_head(grid, scan.landmarks)
    say(f"skin: fitted the template head ({len(head.vertices)} vertices) to a procedural scan "
        f"(level {adaptation.best_level}); skull, muscles and jaw carried along")
    model = SkinModel(head)
    camera = None
    animation = []
    summary = {}
    for stem, title, units, jaw in SKIN_DEMO_EXPRESSIONS:
        result = model.simulate(head.contractions_for(units) if units else None, jaw,
                                options=SimulationOptions(frames=12))
        moved = np.linalg.norm(result.vertices - head.vertices, axis=1)
        summary[stem] = float(moved.max())
        if camera is None:
            camera = render.fit_camera([head.vertices, result.vertices], width=320, height=360)
        images = [render.render_mesh(head.vertices, head.faces, camera=camera),
                  render.render_mesh(result.vertices, head.faces, camera=camera),
                  render.error_heatmap(result.vertices, head.faces, moved, camera=camera)]
        render.save_png(out / f"skin_{stem}.png", render.side_by_side(images, ["fitted scan", title,
                                                                               "displacement (mm)"]))
        frames = [render.render_mesh(f, head.faces, camera=camera) for f in result.frames]
        animation += frames + frames[::-1]
        say(f"skin: {title}: {result.steps} steps, settled after {result.simulated_time * 1e3:.0f} ms of "
            f"simulated time ({result.seconds:.1f} s), largest displacement {moved.max():.1f} mm; "
            f"wrote skin_{stem}.png")
    render.save_gif(out / "skin_expressions.gif", animation, fps=15)
    say("skin: wrote skin_expressions.gif")
    return summary
