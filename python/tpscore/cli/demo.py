"""``tpscore demo``: expression transfer between two real faces, scored against the truth.

The faces are two people of the ICT FaceKit extract that ships with tpscore for the demo
(:mod:`tpscore.showcase.demo_faces`): tpscore scans them in the Bosphorus formats, with a skin
texture of its own, then transfers each expression from the source person's scans to
the target person's neutral scan exactly as ``tpscore transfer`` does with files, and
compares the result with the target person wearing the same expression (the model's
own shapes, which the transfer never sees).

Writes, into the output folder: the input scans under ``scans/`` (``.bnt``, ``.lm3`` and
the ``.png`` each ``.bnt`` names), then for each expression the transferred target as
``.npz``, a textured OBJ (``.obj``, ``.mtl`` and the target's photograph as
``_texture.png``) and
a PLY with vertex colours; a picture of source, expression, measured motion, target,
result and the error against the truth; an animated GIF of a magnitude sweep; and a
page to open in a browser.
Then the physical skin (:func:`run_skin_demo`): the template head fitted to a scan, its
skull, muscles and jaw carried along, smiles, frowns and opens its jaw.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from ..expression import transfer
from ..face import io
from ..face.loading import load_scan
from ..face.resampling import resample_scan
from ..physics import SimulationOptions, SkinModel, fit_head
from ..showcase import datasets, render
from ..showcase.demo_faces import make_demo_scan
from .outputs import transfer_picture, write_result_mesh, write_result_page, write_sweep_gif
from .progress import StepLog

__all__ = ["run_demo", "run_skin_demo", "write_demo_scans", "DEMO_EXPRESSIONS", "SKIN_DEMO_EXPRESSIONS", "SOURCE_PERSON", "TARGET_PERSON"]

#: (file stem, AU weights the source person shows, what is transferred). Sadness and
#: surprise are whole emotions: all the motion the source's scan shows is carried (the
#: source frowns at half strength in its sadness); surprise opens the mouth (the jaw
#: drops, AU26 at 0.4), which the target's mesh shows as an opening.
DEMO_EXPRESSIONS = (
    ("au12", {"12": 1.0}, "12"),
    ("au4", {"4": 1.0}, "4"),
    ("sadness", {"1": 1.0, "4": 0.5, "15": 1.0}, "sadness"),
    ("surprise", {"1": 1.0, "2": 1.0, "5": 1.0, "26": 0.4}, "surprise"),
)
SOURCE_PERSON, TARGET_PERSON = 0, 1

# A scanner's imperfections: depth noise, one dropout per scan, a head not quite
# straight, landmarks clicked half a millimetre off.
_SCAN_OPTIONS = dict(noise_mm=0.1, holes=1, pose_deg=4.0, landmark_noise_mm=0.5)

# Motion smaller than this (mm) is not counted as "where the expression shows".
_MOVING_MM = 0.5


def write_demo_scans(scans_dir) -> dict:
    """Write the demo's input scans (``.bnt``, ``.lm3``, ``.png``) into ``scans_dir``:
    ``source_neutral``, ``target_neutral`` and ``source_<stem>`` for each of
    :data:`DEMO_EXPRESSIONS`. Returns {file stem: (DemoScan, path of its .bnt)}."""
    scans_dir = Path(scans_dir)
    scans_dir.mkdir(parents=True, exist_ok=True)
    scans = {"source_neutral": make_demo_scan(SOURCE_PERSON, None, seed=11, **_SCAN_OPTIONS),
             "target_neutral": make_demo_scan(TARGET_PERSON, None, seed=13, **_SCAN_OPTIONS)}
    for stem, expression, _ in DEMO_EXPRESSIONS:
        scans[f"source_{stem}"] = make_demo_scan(SOURCE_PERSON, expression, seed=12, **_SCAN_OPTIONS)
    return {stem: (scan, scan.write(scans_dir, stem)) for stem, scan in scans.items()}


def run_demo(out_dir="demo-output", *, quiet: bool = False) -> dict:
    """Run the demo; return {stem: {"rms_mm": ..., "noop_rms_mm": ..., "seconds": ...}}.

    ``rms_mm`` is the distance from the transferred target to the true expressive target,
    over the vertices that the true expression moves by more than 0.5 mm; ``noop_rms_mm``
    is the same for the neutral target left as it was (what doing nothing scores).
    """
    out = Path(out_dir)
    say = StepLog(quiet)
    scans = write_demo_scans(out / "scans")
    target = scans["target_neutral"][0]
    source_grid = load_scan(scans["source_neutral"][1])
    target_grid = load_scan(scans["target_neutral"][1])
    say(f"scanned person {SOURCE_PERSON} (source) and person {TARGET_PERSON} (target), neutral and "
        f"{len(DEMO_EXPRESSIONS)} expressions of the source")

    summary = {}
    for stem, expression, request in DEMO_EXPRESSIONS:
        began = time.perf_counter()
        expressive_grid = load_scan(scans[f"source_{stem}"][1])
        grids = (source_grid, expressive_grid, target_grid)
        result = transfer(*grids, request, 1.0, progress=None if quiet else (lambda m: say(f"{stem}: {m}")))
        say(f"{stem}: transferred {'+'.join(result.animation.labels)}")

        mask = result.mask
        truth = target.true_positions(result.neutral[mask], expression)
        error = np.linalg.norm(result.vertices[mask] - truth, axis=1)
        motion = np.linalg.norm(truth - result.neutral[mask], axis=1)
        moving = motion > _MOVING_MM
        summary[stem] = dict(rms_mm=float(np.sqrt(np.mean(error[moving] ** 2))),
                             noop_rms_mm=float(np.sqrt(np.mean(motion[moving] ** 2))))

        io.write_npz(out / f"target_{stem}.npz", **result.to_npz_dict())
        for suffix in ("obj", "ply"):
            write_result_mesh(result, out / f"target_{stem}.{suffix}")
        errors = np.full(mask.shape, np.nan)
        errors[mask] = error
        picture = transfer_picture(grids, result, errors=errors, error_vmax=2.0,
                                   titles={"expressive": f"source {stem}", "error": "error vs truth (mm)"})
        io.write_png(out / f"transfer_{stem}.png", picture)
        write_sweep_gif(result, out / f"sweep_{stem}.gif")
        write_result_page(result, out / f"result_{stem}.html",
                          title=f"tpscore demo: {stem} carried from person {SOURCE_PERSON} to person {TARGET_PERSON}")
        summary[stem]["seconds"] = time.perf_counter() - began
        say(f"{stem}: rms error {summary[stem]['rms_mm']:.2f} mm where the truth moves "
            f"(leaving the target neutral: {summary[stem]['noop_rms_mm']:.2f} mm); wrote target_{stem}.npz, "
            f".obj/.mtl/_texture.png, .ply, transfer_{stem}.png, sweep_{stem}.gif, result_{stem}.html")
    summary["skin"] = run_skin_demo(out, quiet=quiet)
    say(f"done: outputs in {out.resolve()}; open a result_*.html in a browser")
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
    say = StepLog(quiet)

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
        state = ("settled after" if result.settled else "did not settle within")
        say(f"skin: {title}: {result.steps} steps, {state} {result.simulated_time * 1e3:.0f} ms of "
            f"simulated time ({result.seconds:.1f} s), largest displacement {moved.max():.1f} mm; "
            f"wrote skin_{stem}.png")
    render.save_gif(out / "skin_expressions.gif", animation, fps=15)
    say("skin: wrote skin_expressions.gif")
    return summary
