"""The ``tpscore adapt`` subcommand: fit a template mesh to a scan.

    tpscore adapt [TEMPLATE --template-landmarks T.lm3] SCAN [--scan-landmarks S.lm3]
                  --out fitted.obj [--png fit.png] [--levels 6] [--calibration similarity]

TEMPLATE is any mesh trimesh reads, with its landmarks; without it the shipped template
head (the physical skin's, ``tpscore.physics.load_template()``, with its 22 landmarks)
is fitted. SCAN is a mesh or a Bosphorus .bnt. The fitted mesh keeps the template's
vertex order, count and faces, in the scan's frame.
"""
from __future__ import annotations


from ..adaptation import AdaptOptions, adapt
from ..face import io
from ..physics import load_template
from ..showcase import render
from .arguments import integer, read_scan_surface, read_scan_landmarks
from .progress import StepLog

__all__ = ["add_adapt_parser", "adapt_command"]


def add_adapt_parser(sub) -> None:
    p = sub.add_parser("adapt", help="deform a template mesh onto a scan (global RBF + multilevel CSRBF)")
    p.add_argument("meshes", nargs="+", metavar="[TEMPLATE] SCAN",
                   help="template mesh (OBJ, PLY, ...; default: the shipped template head) and the scan "
                        "(a mesh or a Bosphorus .bnt)")
    p.add_argument("--template-landmarks", metavar="FILE",
                   help=".lm3, .csv or .json (needed with TEMPLATE; the shipped template has its own)")
    p.add_argument("--scan-landmarks", metavar="FILE", help="default: the .lm3/.csv/.json beside SCAN, else landmarks detected from it")
    p.add_argument("--out", required=True, metavar="MESH", help="fitted template (OBJ or PLY)")
    p.add_argument("--png", metavar="PNG", help="render scan, template and fit side by side")
    p.add_argument("--levels", type=integer(1), default=6, help="largest number of levels (default 6)")
    p.add_argument("--calibration", choices=["similarity", "axes", "none"], default="similarity")
    p.add_argument("--rho", type=float, default=30.0, help="error coefficient of the global RBF (mm, default 30)")
    p.add_argument("--refinement", choices=["surface", "interpolate"], default="surface",
                   help="surface: point-to-plane levels (default); interpolate: the published ray pairs")
    p.add_argument("--quiet", action="store_true")


def adapt_command(args) -> int:
    say = StepLog(args.quiet)

    if len(args.meshes) > 2:
        raise ValueError(f"give SCAN, or TEMPLATE and SCAN; got {len(args.meshes)} paths")
    args.template, args.scan = args.meshes if len(args.meshes) == 2 else (None, args.meshes[0])
    if args.template is None:
        if args.template_landmarks is not None:
            raise ValueError("--template-landmarks needs TEMPLATE (the shipped template has its own landmarks)")
        head = load_template()
        template_vertices, template_faces, template_landmarks = head.vertices, head.faces, head.landmark_vertices
    else:
        if args.template_landmarks is None:
            raise ValueError(f"--template-landmarks is needed with TEMPLATE {args.template!r}")
        template_vertices, template_faces = io.read_mesh(args.template)
        if len(template_faces) == 0:
            raise ValueError(f"{args.template!r}: the template has no faces; adaptation needs a mesh")
        template_landmarks = io.read_landmarks(args.template_landmarks)
    scan = read_scan_surface(args.scan)
    scan_landmarks = read_scan_landmarks(args.scan, args.scan_landmarks)
    say(f"read template ({len(template_vertices)} vertices) and scan ({len(scan[0])} vertices)")

    def progress(level) -> None:
        say(f"level {level.level} ({level.method}, {level.pairs} pairs): Ed {level.distance_error:.3f} mm^2, "
            f"coverage {level.coverage:.2f}")

    options = AdaptOptions(levels=args.levels, calibration=args.calibration, rho=args.rho,
                           refinement=args.refinement)
    result = adapt((template_vertices, template_faces), scan, template_landmarks, scan_landmarks,
                   options=options, progress=progress)
    say(f"kept level {result.best_level}")
    io.write_mesh(args.out, result.vertices, template_faces)
    say(f"wrote {args.out}")
    if args.png:
        camera = render.fit_camera([scan[0], result.vertices])
        images = [render.render_mesh(scan[0], scan[1], camera=camera),
                  render.render_mesh(result.transform.apply_inverse(template_vertices), template_faces, camera=camera),
                  render.render_mesh(result.vertices, template_faces, camera=camera)]
        render.save_png(args.png, render.side_by_side(images, ["scan", "template (calibrated)", "fitted"]))
        say(f"wrote {args.png}")
    return 0
