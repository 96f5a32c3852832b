"""A fitted scan smiles, frowns and opens its jaw by muscle contraction.

:func:`run_skin_demo` makes a procedural scan (tpscore's own faces: an identity the
template was not built from, with scanner noise and a little pose), fits the
template head to it with :func:`tpscore.adapt` and carries the skull, muscles and jaw
along, then simulates three expressions with the physical skin and writes, for each, a
picture (rest, settled, displacement) and, for all three, an animated GIF.
``tpscore demo`` calls it after the expression-transfer demo.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

__all__ = ["run_skin_demo", "SKIN_DEMO_EXPRESSIONS"]

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
    from .. import datasets, render
    from ..preprocess import resample_scan
    from .fitting import fit_head
    from .simulation import SkinModel

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
        result = model.simulate(head.contractions_for(units) if units else None, jaw, frames=12)
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
