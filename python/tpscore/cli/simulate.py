"""The ``tpscore simulate`` subcommand: animate a head with the physical skin.

    tpscore simulate SCAN [--scan-landmarks S.lm3] --au 12:0.6 [--jaw 10] --out settled.npz
    tpscore simulate --fitted FITTED.obj --contract zygomaticus_major_left=0.5 --gif smile.gif

SCAN (a Bosphorus .bnt or a mesh, with landmarks) gets the template head fitted to it
first (``tpscore.adapt``) and its physical structure carried along; a FITTED mesh is
the template already fitted by other means (the template's vertex count and order).
Outputs: the settled skin (.npz with the rest skin, the layers, the animation frames
and their times; or a mesh), pictures and an animated GIF.
"""
from __future__ import annotations


import numpy as np

from ..face import io
from ..physics import SimulationOptions, SkinModel, carry_head, deform_from_vertices, fit_head, load_template
from ..showcase import render
from .arguments import read_scan_surface, read_scan_landmarks
from .progress import StepLog

__all__ = ["add_simulate_parser", "simulate_command", "parse_contractions"]


def add_simulate_parser(sub) -> None:
    p = sub.add_parser("simulate", help="contract muscles and open the jaw of a fitted head (physical skin)")
    p.add_argument("scan", nargs="?", metavar="SCAN", help="scan to fit the template head to (.bnt or mesh)")
    p.add_argument("--scan-landmarks", metavar="FILE", help="landmarks of SCAN (default: the .lm3/.csv/.json beside it, else detected from it)")
    p.add_argument("--fitted", metavar="MESH", help="the template already fitted to a face, vertex for vertex")
    p.add_argument("--template", metavar="NPZ", help="a head file (default: the shipped template)")
    p.add_argument("--au", default="", help="AU intensities: '12', '12:0.6,4:0.3', '12L'")
    p.add_argument("--contract", default="", help="muscle contractions: 'mentalis=0.3,orbicularis_oris=0.2'")
    p.add_argument("--jaw", type=float, default=0.0, help="jaw opening angle in degrees (0-30)")
    p.add_argument("--integrator", choices=["symplectic", "implicit"], default="symplectic")
    p.add_argument("--dt", type=float, help="step in seconds (default: the integrator's)")
    p.add_argument("--out", metavar="NPZ", help="write the settled skin, the rest skin, layers and frames")
    p.add_argument("--mesh", metavar="OBJ|PLY", help="write the settled skin as a mesh")
    p.add_argument("--png", metavar="PNG", help="write rest and settled skin and the displacement side by side")
    p.add_argument("--gif", metavar="GIF", help="write the animation from rest to the settled skin and back")
    p.add_argument("--list-muscles", action="store_true", help="print the head's muscles and AUs and stop")
    p.add_argument("--quiet", action="store_true")


def parse_contractions(head, au_text: str, muscle_text: str) -> dict:
    """Contractions from ``--au`` ('12:0.6,4') and ``--contract`` ('mentalis=0.3') text."""
    contractions: dict[str, float] = {}
    for item in (t.strip() for t in au_text.split(",") if t.strip()):
        code, _, value = item.partition(":")
        try:
            level = float(value) if value else 1.0
        except ValueError:
            raise ValueError(f"--au: {item!r} is not CODE or CODE:LEVEL") from None
        for muscle, c in head.contractions_for({code: level}).items():
            contractions[muscle] = contractions.get(muscle, 0.0) + c
    for item in (t.strip() for t in muscle_text.split(",") if t.strip()):
        name, sep, value = item.partition("=")
        try:
            level = float(value)
        except ValueError:
            raise ValueError(f"--contract: {item!r} is not MUSCLE=LEVEL") from None
        if not sep:
            raise ValueError(f"--contract: {item!r} is not MUSCLE=LEVEL")
        contractions[name.strip()] = contractions.get(name.strip(), 0.0) + level
    return contractions


def _check_contractions(head, contractions: dict) -> None:
    for name, value in contractions.items():
        if name not in head.muscle_names:
            raise ValueError(f"contractions: unknown muscle {name!r}; known: {', '.join(head.muscle_names)}")
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"contractions must lie in [0, 1], got {value:g} for {name!r}")


def simulate_command(args) -> int:
    say = StepLog(args.quiet)

    template = load_template(args.template)
    if args.list_muscles:
        for muscle in template.muscles:
            print(f"{muscle.name} ({muscle.kind}; regions {', '.join(muscle.regions)})")
        for code, recipe in template.action_units.items():
            print(f"AU{code}: " + ", ".join(f"{m} {v:g}" for m, v in recipe.items()))
        return 0
    if (args.scan is None) == (args.fitted is None):
        raise ValueError("give a SCAN to fit the template to, or --fitted MESH (one of them)")
    # Check the contractions on the template (its muscles are the fitted head's) before
    # spending a fit on them.
    contractions = parse_contractions(template, args.au, args.contract)
    _check_contractions(template, contractions)
    if args.scan is not None:
        scan = read_scan_surface(args.scan)
        landmarks = read_scan_landmarks(args.scan, args.scan_landmarks)
        head, adaptation = fit_head(scan, landmarks, template)
        say(f"fitted the template head to {args.scan} (level {adaptation.best_level}) and carried its skull, "
            f"muscles and jaw along")
    else:
        vertices, _ = io.read_mesh(args.fitted)
        head = carry_head(template, deform_from_vertices(template, vertices), vertices)
        say(f"carried the template's structure onto {args.fitted}")
    model = SkinModel(head)
    result = model.simulate(contractions, args.jaw, options=SimulationOptions(integrator=args.integrator, dt=args.dt))
    active = ", ".join(f"{k} {v:.2f}" for k, v in result.contractions.items()) or "no muscle"
    say(f"simulated {active}, jaw {result.jaw_deg:.1f} deg: {result.steps} steps of {result.dt * 1e3:.3f} ms, "
        f"{'settled' if result.settled else 'NOT settled'} after {result.simulated_time * 1e3:.0f} ms "
        f"({result.seconds:.1f} s)")
    if args.out:
        io.write_npz(args.out, vertices=result.vertices, neutral=head.vertices, faces=head.faces,
                     layers=result.layers, times=result.times, frames=result.frames,
                     muscles=np.array(list(result.contractions), dtype=str),
                     contractions=np.array(list(result.contractions.values()), dtype=np.float64),
                     jaw_deg=np.array(result.jaw_deg))
        say(f"wrote {args.out}")
    if args.mesh:
        io.write_mesh(args.mesh, result.vertices, head.faces)
        say(f"wrote {args.mesh}")
    if args.png or args.gif:
        camera = render.fit_camera([head.vertices, result.vertices])
        if args.png:
            moved = np.linalg.norm(result.vertices - head.vertices, axis=1)
            images = [render.render_mesh(head.vertices, head.faces, camera=camera),
                      render.render_mesh(result.vertices, head.faces, camera=camera),
                      render.error_heatmap(result.vertices, head.faces, moved, camera=camera)]
            render.save_png(args.png, render.side_by_side(images, ["rest", "settled", "displacement (mm)"]))
            say(f"wrote {args.png}")
        if args.gif:
            frames = [render.render_mesh(f, head.faces, camera=camera) for f in result.frames]
            render.save_gif(args.gif, frames + frames[::-1][1:-1], fps=15)
            say(f"wrote {args.gif}")
    return 0
