"""``tpscore demo``: expression transfer between two real faces, scored against the truth.

The faces are two people of the ICT FaceKit extract that ships with tpscore for the demo
(:mod:`tpscore.demo_faces`): tpscore scans them in the Bosphorus formats, with a skin
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
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..demo_faces import make_demo_scan
from ..expression import transfer
from ..face import io
from ..face.grid import load_scan
from .outputs import transfer_picture, write_result_mesh, write_result_page, write_sweep_gif

__all__ = ["run_demo", "DEMO_EXPRESSIONS", "SOURCE_PERSON", "TARGET_PERSON"]

#: (file stem, AU weights the source person shows, what is transferred). Sadness is the
#: prototype the AU library knows (AU1 + AU4 + AU15); the source frowns at half strength.
DEMO_EXPRESSIONS = (
    ("au12", {"12": 1.0}, "12"),
    ("au4", {"4": 1.0}, "4"),
    ("sadness", {"1": 1.0, "4": 0.5, "15": 1.0}, "sadness"),
)
SOURCE_PERSON, TARGET_PERSON = 0, 1

# A scanner's imperfections: depth noise, one dropout per scan, a head not quite
# straight, landmarks clicked half a millimetre off.
_SCAN_OPTIONS = dict(noise_mm=0.1, holes=1, pose_deg=4.0, landmark_noise_mm=0.5)

# Motion smaller than this (mm) is not counted as "where the expression shows".
_MOVING_MM = 0.5


def run_demo(out_dir="demo-output", *, quiet: bool = False) -> dict:
    """Run the demo; return {stem: {"rms_mm": ..., "noop_rms_mm": ..., "seconds": ...}}.

    ``rms_mm`` is the distance from the transferred target to the true expressive target,
    over the vertices that the true expression moves by more than 0.5 mm; ``noop_rms_mm``
    is the same for the neutral target left as it was (what doing nothing scores).
    """
    out = Path(out_dir)
    scans_dir = out / "scans"
    scans_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    def say(message):
        if not quiet:
            print(f"[{time.perf_counter() - start:6.2f} s] {message}", flush=True)

    source = make_demo_scan(SOURCE_PERSON, None, seed=11, **_SCAN_OPTIONS)
    target = make_demo_scan(TARGET_PERSON, None, seed=13, **_SCAN_OPTIONS)
    source_grid = load_scan(source.write(scans_dir, "source_neutral"))
    target_grid = load_scan(target.write(scans_dir, "target_neutral"))
    say(f"scanned person {SOURCE_PERSON} (source) and person {TARGET_PERSON} (target) neutral")

    summary = {}
    for stem, expression, request in DEMO_EXPRESSIONS:
        began = time.perf_counter()
        expressive = make_demo_scan(SOURCE_PERSON, expression, seed=12, **_SCAN_OPTIONS)
        expressive_grid = load_scan(expressive.write(scans_dir, f"source_{stem}"))
        say(f"{stem}: scanned the source's expression")
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
    say(f"done: outputs in {out.resolve()}; open a result_*.html in a browser")
    return summary
