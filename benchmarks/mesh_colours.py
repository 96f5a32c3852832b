"""Transfers from scans given as meshes with their colours score as from the .bnt scans.

Each development scan (.bnt with its .png) is written again with tpscore's own writers
as a textured OBJ (``write_textured_obj``: .obj, .mtl, _texture.png) and as a PLY with
vertex colours (the image sampled at each point's u,v), every point of the scan a vertex
and the scan's lattice its triangles, with the .lm3 beside each. The same pairs are
transferred from the three kinds of input and scored against the target's ground-truth
sidecars (tpscore.batch.score_with_sidecars, the arithmetic of
../shared/tools/score_transfer.py)::

    python benchmarks/mesh_colours.py [--scans FOLDER] [--code LFAU_25_0] [--pairs 6]

(the scans are made with ../shared/tools/make_scans.py into bench-output/scans_colours, or
--scans, where missing)

Writes the table to stdout (and to bench-output/mesh_colours.md).
"""
from __future__ import annotations

import argparse
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from shared_data import REPOSITORY, shared_dir
from report import write_report

REQUESTS = {"LFAU_25_0": "25", "E_SURPRISE_0": "surprise", "LFAU_12_0": "12", "UFAU_2_0": "2"}


def scan_path(scans: Path, subject: int, code: str) -> Path:
    return scans / f"bs{subject:03d}" / f"bs{subject:03d}_{code}.bnt"


def convert(bnt: Path, out: Path) -> tuple[Path, Path, Path]:
    """The .bnt scan as a textured OBJ, as a vertex-coloured PLY and as a PLY without
    colour (the floor: the motion from the geometry alone), landmarks beside."""
    from tpscore.face import io
    from tpscore.face.image import sample_image
    from tpscore.mesh import grid_triangles

    out.mkdir(parents=True, exist_ok=True)
    obj, ply, bare = out / f"{bnt.stem}.obj", out / f"{bnt.stem}.ply", out / f"{bnt.stem}_bare.ply"
    if obj.is_file() and ply.is_file() and bare.is_file():
        return obj, ply, bare
    scan = io.read_bnt(bnt)
    image = io.read_image(bnt.parent / scan.image_name)
    keep = scan.valid.reshape(-1)
    index = np.full(keep.size, -1, dtype=np.int64)
    index[keep] = np.arange(np.count_nonzero(keep))
    faces = index[grid_triangles(scan.valid)]
    vertices = scan.points.reshape(-1, 3)[keep]
    uv = scan.uv.reshape(-1, 2)[keep]
    io.write_textured_obj(obj, vertices, faces, uv, image)
    colours = np.round(sample_image(image, uv)).astype(np.uint8)
    io.write_mesh(ply, vertices, faces, vertex_colors=colours)
    io.write_mesh(bare, vertices, faces)
    for path in (obj, ply, bare):
        shutil.copy(bnt.with_suffix(".lm3"), path.with_suffix(".lm3"))
    return obj, ply, bare


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=Path, default=REPOSITORY / "bench-output" / "scans_colours")
    parser.add_argument("--code", default="LFAU_25_0", choices=sorted(REQUESTS))
    parser.add_argument("--pairs", type=int, default=6, help="source s -> target s + 1, s = 0, 1, ...")
    parser.add_argument("--out", type=Path, default=REPOSITORY / "bench-output")
    args = parser.parse_args(argv)
    shared = shared_dir()
    if shared is None:
        print("skipped: needs the shared folder (the scans' generator and the face model)", file=sys.stderr)
        return 0
    from fidelity import ensure_scans

    ensure_scans(shared, args.scans, list(range(args.pairs + 1)), codes=["N_N_0", args.code])
    import tpscore
    from tpscore.batch import score_with_sidecars

    faces = np.load(shared / "data" / "ict-facekit" / "face_model.npz")["faces"]
    meshes = args.out / "mesh_colours"
    request = REQUESTS[args.code]
    kinds = ("bnt + png", "textured OBJ", "vertex-coloured PLY", "PLY without colour")
    ratios = {kind: [] for kind in kinds}
    seconds = {kind: [] for kind in kinds}
    texture_warnings = {kind: 0 for kind in kinds}
    for source in range(args.pairs):
        target = source + 1
        bnts = [scan_path(args.scans, source, "N_N_0"), scan_path(args.scans, source, args.code),
                scan_path(args.scans, target, "N_N_0")]
        converted = [convert(path, meshes) for path in bnts]
        inputs = {kinds[0]: bnts, kinds[1]: [c[0] for c in converted], kinds[2]: [c[1] for c in converted],
                  kinds[3]: [c[2] for c in converted]}
        a_gt = str(bnts[2].with_suffix("")) + "_gt.npz"
        b_gt = str(scan_path(args.scans, target, args.code).with_suffix("")) + "_gt.npz"
        line = [f"{source}->{target}"]
        for kind in kinds:
            start = time.perf_counter()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                grids = tpscore.load_scans([str(p) for p in inputs[kind]])
                result = tpscore.transfer(*grids, request)
            seconds[kind].append(time.perf_counter() - start)
            texture_warnings[kind] += sum(issubclass(w.category, tpscore.TextureWarning) for w in caught)
            score = score_with_sidecars(result.vertices, result.neutral, grids[2].mask, a_gt, b_gt, faces)
            ratios[kind].append(score["residual_ratio"])
            line.append(f"{kind}: {score['residual_ratio']:.3f}")
        print("  ".join(line), flush=True)
    rows = [f"| input | residual ratio (mean of {args.pairs}) | load + transfer s | texture warnings |",
            "|---|---:|---:|---:|"]
    for kind in kinds:
        rows.append(f"| {kind} | {np.mean(ratios[kind]):.3f} | {np.mean(seconds[kind]):.2f} | "
                    f"{texture_warnings[kind]} |")
    table = "\n".join([f"{args.code} ({request}), pairs s -> s + 1 for s = 0..{args.pairs - 1}", "", *rows])
    write_report(args.out / "mesh_colours.md", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
