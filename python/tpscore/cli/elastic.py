"""``tpscore elastic``: learn expressions on a source face and clone them onto a target.

    tpscore elastic --out DIR [--expressions smile,frown,...]
    tpscore elastic --source SRC.npz --target TGT.npz --out DIR
    tpscore elastic --face-model face_model.npz [--source-subject 0] [--target-subject 1]
                    [--expressions mouthSmile_L,jawOpen,...] [--remesh-target] --out DIR

Inputs: without ``--source`` or ``--face-model``, tpscore's procedural faces
(:func:`tpscore.showcase.datasets.elastic_faces`: the demo's two people as meshes, with smile,
frown, brows, dimpler, sad_mouth and stretch on the neutral's vertices; the report then
also gives each clone's distance from the target's own expression). Or ``.npz`` files:

* SRC: ``neutral`` (n, 3) mm, ``faces`` (m, 3), ``landmarks`` (22, 3) (Bosphorus order, NaN
  where missing), ``expressions`` (e, n, 3) expressive meshes with the neutral's
  connectivity, optional ``names`` (e,).
* TGT: ``vertices`` (p, 3), ``faces`` (q, 3), ``landmarks`` (22, 3); any mesh structure.
* Or the ICT face-area model: subjects are its neutral + identity modes (weights drawn
  N(0, 1) from the subject number) and the expressions its expression modes;
  ``--remesh-target`` resamples the target as a 150 x 150 height-field grid.

Outputs in DIR: ``elastic.npz`` (control point names, source and target handles,
learned and cloned parameters, cloned target meshes), ``report.md`` (per-expression
reconstruction error, storage), and one picture per expression
``<name>.png`` (source example, its reconstruction, target neutral, cloned target).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .._files import atomic_write
from ..elastic import ElasticFace, ElasticOptions
from ..face import io
from ..mesh import height_field_remesh
from ..showcase import datasets, render
from .arguments import integer
from .progress import StepLog

__all__ = ["add_elastic_parser", "elastic_command"]

ICT_EXPRESSIONS = "browInnerUp_L,browDown_L,mouthSmile_L,mouthFrown_L,jawOpen,mouthPucker"


def add_elastic_parser(subparsers) -> None:
    """Register the ``elastic`` sub-command on an argparse subparsers object."""
    p = subparsers.add_parser(
        "elastic", help="learn expressions with the elastic model and clone them onto another face")
    source = p.add_mutually_exclusive_group()
    source.add_argument("--source", metavar="NPZ", help="source neutral, faces, landmarks and expressive meshes")
    source.add_argument("--face-model", metavar="NPZ", help="the ICT face-area model (face_model.npz)")
    p.add_argument("--target", metavar="NPZ", help="target vertices, faces, landmarks (with --source)")
    p.add_argument("--source-subject", type=integer(0), default=0, help="ICT subject of the source (default 0)")
    p.add_argument("--target-subject", type=integer(0), default=1, help="ICT subject of the target (default 1)")
    p.add_argument("--expressions", default=None,
                   help="comma-separated expression names: of the procedural faces (default: all of "
                        f"{','.join(datasets.ELASTIC_EXPRESSIONS)}), or ICT names with --face-model "
                        f"(default: {ICT_EXPRESSIONS})")
    p.add_argument("--remesh-target", action="store_true",
                   help="resample the ICT target as a 150 x 150 height-field grid (a different mesh structure)")
    p.add_argument("--fixed-factor", type=float, default=1.8,
                   help="fixed region: beyond this multiple of the nose-tip-to-forehead distance (default 1.8)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--no-pictures", action="store_true", help="skip the PNG pictures")
    p.add_argument("--quiet", action="store_true")


def _load_npz(path: str, fields: tuple[str, ...]) -> dict:
    return io.read_npz(path, fields, what="an elastic model input (.npz)")


def _check_face_model(model: dict, path: str) -> None:
    """The ICT face-area model's arrays, checked against each other before use (a forged
    file would otherwise fail deep inside NumPy, or index out of range)."""
    where = repr(str(path))

    def fail(problem: str):
        raise ValueError(f"{where}: not an ICT face-area model: {problem}")

    def numeric(name: str, ndim: int, kind: str = "f"):
        array = model[name]
        if array.ndim != ndim or array.dtype.kind not in ("iu" if kind == "i" else "fiu"):
            fail(f"{name} must be a {ndim}-D {'integer' if kind == 'i' else 'numeric'} array, "
                 f"got shape {array.shape} and dtype {array.dtype}")
        if kind == "f" and not np.isfinite(array).all():
            fail(f"{name} has NaN or infinite values")
        return array

    neutral = numeric("neutral", 2)
    n = len(neutral)
    if neutral.shape[1:] != (3,) or n < 3:
        fail(f"neutral must have shape (n, 3) with n >= 3, got {neutral.shape}")
    faces = numeric("faces", 2, "i")
    if faces.shape[1:] != (3,) or len(faces) == 0 or faces.min() < 0 or faces.max() >= n:
        fail(f"faces must be (m, 3) indices into the {n} vertices")
    for name in ("identity_modes", "expression_modes"):
        modes = numeric(name, 3)
        if modes.shape[1:] != (n, 3):
            fail(f"{name} must have shape (k, {n}, 3), got {modes.shape}")
    if model["expression_names"].shape != (len(model["expression_modes"]),):
        fail(f"expression_names must name the {len(model['expression_modes'])} expression modes")
    index = numeric("bosphorus_index", 1, "i")
    if index.shape != (22,) or index.min() < 0 or index.max() >= n:
        fail(f"bosphorus_index must be 22 vertex indices in [0, {n})")


def _subject(model: dict, subject: int) -> np.ndarray:
    weights = np.random.default_rng(subject).normal(size=len(model["identity_modes"]))
    return model["neutral"].astype(np.float64) + np.tensordot(weights, model["identity_modes"].astype(np.float64), 1)


def elastic_command(args) -> int:
    """Run ``tpscore elastic`` from parsed arguments; returns the exit status."""
    step = StepLog(args.quiet)
    target_truth = None

    if args.face_model:
        model = _load_npz(args.face_model, ("neutral", "faces", "identity_modes", "expression_names",
                                            "expression_modes", "bosphorus_index"))
        _check_face_model(model, args.face_model)
        faces = model["faces"].astype(np.int64)
        index = model["bosphorus_index"].astype(np.int64)
        source_neutral = _subject(model, args.source_subject)
        all_names = [str(n) for n in model["expression_names"]]
        names = [n.strip() for n in (args.expressions or ICT_EXPRESSIONS).split(",") if n.strip()]
        unknown = [n for n in names if n not in all_names]
        if unknown or not names:
            raise ValueError(f"--expressions: unknown name(s) {', '.join(unknown) or '(none given)'}; "
                             f"known: {', '.join(all_names)}")
        modes = model["expression_modes"].astype(np.float64)
        examples = np.stack([source_neutral + modes[all_names.index(n)] for n in names])
        source_landmarks = source_neutral[index]
        target_vertices = _subject(model, args.target_subject)
        target_landmarks = target_vertices[index]
        target_faces = faces
        if args.remesh_target:
            target_vertices, target_faces, _, _ = height_field_remesh(target_vertices, faces, target_landmarks[13])
        step(f"built ICT subjects {args.source_subject} (source) and {args.target_subject} (target)")
    elif args.source is None:
        known = dict(datasets.ELASTIC_EXPRESSIONS)
        names = [n.strip() for n in (args.expressions or ",".join(known)).split(",") if n.strip()]
        unknown = [n for n in names if n not in known]
        if unknown or not names:
            raise ValueError(f"--expressions: unknown name(s) {', '.join(unknown) or '(none given)'}; "
                             f"known: {', '.join(known)}")
        if args.target:
            raise ValueError("--target is used with --source; the procedural faces bring their own target")
        src, tgt = datasets.elastic_faces({n: known[n] for n in names})
        source_neutral, faces, source_landmarks, examples = src.neutral, src.faces, src.landmarks, src.expressive
        target_vertices, target_faces, target_landmarks = tgt.neutral, tgt.faces, tgt.landmarks
        target_truth = tgt.expressive
        step(f"built the procedural source and target faces ({len(source_neutral)} and "
             f"{len(target_vertices)} vertices, {len(names)} expressions)")
    else:
        if not args.target:
            raise ValueError("--target is needed with --source")
        src = _load_npz(args.source, ("neutral", "faces", "landmarks", "expressions"))
        tgt = _load_npz(args.target, ("vertices", "faces", "landmarks"))
        source_neutral, faces = src["neutral"], src["faces"]
        source_landmarks = src["landmarks"]
        examples = src["expressions"]
        names = [str(n) for n in src["names"]] if "names" in src else [f"expr{i}" for i in range(len(examples))]
        target_vertices, target_faces, target_landmarks = tgt["vertices"], tgt["faces"], tgt["landmarks"]
        step(f"read {args.source} and {args.target}")

    source = ElasticFace(source_neutral, faces, landmarks=source_landmarks,
                         options=ElasticOptions(fixed_factor=args.fixed_factor))
    step(f"source: {len(source.vertices)} vertices, {len(source.handles)} control points, basis in "
         f"{sum(source.timings.values()) * 1e3:.0f} ms")
    learned = source.fit(examples, names)
    step(f"learned {len(names)} expressions; mean reconstruction RMS {learned.rms_mm.mean():.2f} mm")
    target = source.clone_to((target_vertices, target_faces), target_landmarks=target_landmarks,
                             options=ElasticOptions(fixed_factor=args.fixed_factor, unanchored="fix"))
    cloned = target.deform(target.expressions.parameters)
    step(f"cloned onto the target ({len(target.vertices)} vertices)")

    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot create the folder {str(out)!r}: {exc.strerror}") from None
    io.write_npz(
        out / "elastic.npz", control_point_names=np.array(source.control_point_names),
        source_handles=source.handles, target_handles=target.handles, expression_names=np.array(names),
        source_parameters=learned.parameters, target_parameters=target.expressions.parameters,
        rms_mm=learned.rms_mm, target_vertices=target.vertices, target_faces=target.faces,
        cloned_vertices=cloned)
    storage = source.storage()
    lines = ["| expression | motion RMS (mm) | reconstruction RMS (mm) | max error (mm) |", "|---|---:|---:|---:|"]
    lines += [f"| {n} | {m:.2f} | {r:.2f} | {x:.2f} |"
              for n, m, r, x in zip(names, learned.motion_rms_mm, learned.rms_mm, learned.max_mm)]
    lines += ["", f"Storage: parameters + basis / per-vertex displacements = {storage['ratio']:.3f}; "
                  f"parameters only = {storage['ratio_parameters_only']:.4f}."]
    if target_truth is not None:
        # the procedural target wears each expression too: the clone's distance from it
        def rms(a, b):
            return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))

        lines += ["", "| expression | clone to the target's own expression RMS (mm) | target neutral to it (mm) |",
                  "|---|---:|---:|"]
        lines += [f"| {n} | {rms(cloned[i], target_truth[i]):.2f} | {rms(target_vertices, target_truth[i]):.2f} |"
                  for i, n in enumerate(names)]
    atomic_write(out / "report.md", ("\n".join(lines) + "\n").encode("utf-8"))
    if not args.no_pictures:
        source_camera = render.fit_camera([source.vertices], width=320, height=380)
        target_camera = render.fit_camera([target.vertices], width=320, height=380)
        target_neutral = render.render_mesh(target.vertices, target.faces, camera=target_camera)
        for i, name in enumerate(names):
            pictures = [
                render.render_mesh(examples[i], source.faces, camera=source_camera),
                render.render_mesh(source.deform(learned.parameters[i]), source.faces, camera=source_camera),
                target_neutral,
                render.render_mesh(cloned[i], target.faces, camera=target_camera),
            ]
            titles = [f"source {name}", f"reconstructed ({learned.rms_mm[i]:.2f} mm RMS)", "target neutral", "cloned"]
            safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
            render.save_png(out / f"{safe}.png", render.side_by_side(pictures, titles))
        step(f"wrote {len(names)} pictures")
    step(f"wrote {out / 'elastic.npz'} and {out / 'report.md'}")
    return 0
