#!/usr/bin/env python3
"""Write tpscore's demo-face extract (python/tpscore/data/ict_demo_faces.npz) from the
ICT FaceKit face model in ../shared.

The demo (``tpscore demo``) shows expression transfer between real face shapes, so the
package ships a small part of the ICT FaceKit model (MIT licence; the licence text is
copied beside the extract): the face area a frontal scanner sees, a few people, and the
expression shapes of the action units tpscore implements. The scans, their skin
texture and their ground truth are made from it at run time by
:mod:`tpscore.showcase.demo_faces`; the transfer method itself never reads it.

    python tools/make_demo_faces.py [--model ../shared/data/ict-facekit/face_model.npz]

What is kept, and why it is small (about 0.3 MB):

- the triangles whose three corners lie within ``--crop-mm`` (100 mm, what the
  benchmark's scanner sees) of the generic face's nose tip, and the vertices they use;
- the generic neutral face, each person as a delta from it, and each expression shape
  as a delta: every coordinate rounded to 0.01 mm and stored as int16 (the model's own
  text files hold about 0.01 mm; a face scanner's noise is ten times that);
- the 22 Bosphorus landmark vertices and the iBUG-68 vertices inside the crop (brows,
  eyes, nose, lips), which the skin texture uses to place brows and lips.

The people are draws of the model's identity weights, w ~ N(0, 1) per mode, as the
model's own sampler draws them, from a seed of their own, so they are none of the
benchmark's subjects.
"""
from __future__ import annotations

import argparse
import io
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

REPOSITORY = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = REPOSITORY.parent / "shared" / "data" / "ict-facekit" / "face_model.npz"
OUTPUT = REPOSITORY / "python" / "tpscore" / "data" / "ict_demo_faces.npz"
LICENCE_OUTPUT = REPOSITORY / "python" / "tpscore" / "data" / "ict_facekit_LICENSE.txt"

#: AU -> ICT expression shapes, as the benchmark's scan generator maps them (one shape
#: per side for the two-sided AUs; AU17 and AU26 have one shape for both sides). AU5
#: and AU26 make the demo's open-mouthed surprise; AU43 closes the eyes (the tests' lids).
AU_SHAPES = {
    "1": ("browInnerUp_L", "browInnerUp_R"),
    "2": ("browOuterUp_L", "browOuterUp_R"),
    "4": ("browDown_L", "browDown_R"),
    "12": ("mouthSmile_L", "mouthSmile_R"),
    "14": ("mouthDimple_L", "mouthDimple_R"),
    "15": ("mouthFrown_L", "mouthFrown_R"),
    "17": ("mouthShrugLower",),
    "20": ("mouthStretch_L", "mouthStretch_R"),
    "5": ("eyeWide_L", "eyeWide_R"),
    "26": ("jawOpen",),
    "43": ("eyeBlink_L", "eyeBlink_R"),
}

QUANTUM_MM = 0.01
PEOPLE = 4
# A seed no benchmark subject uses (those are default_rng(subject + offset)).
PEOPLE_SEED = (0x7D5C, 19)


def _quantise(values: np.ndarray, what: str) -> np.ndarray:
    steps = np.round(np.asarray(values, dtype=np.float64) / QUANTUM_MM)
    if np.abs(steps).max() > np.iinfo(np.int16).max:
        raise ValueError(f"{what} reaches {np.abs(values).max():.1f} mm, beyond int16 at {QUANTUM_MM} mm")
    return steps.astype(np.int16)


def extract(model_path: Path, crop_mm: float) -> dict:
    with np.load(model_path) as model:
        neutral = model["neutral"].astype(np.float64)
        faces = model["faces"].astype(np.int64)
        identity_modes = model["identity_modes"].astype(np.float64)
        names = [str(n) for n in model["expression_names"]]
        expression_modes = model["expression_modes"]
        bosphorus_index = model["bosphorus_index"].astype(np.int64)
        landmarks68 = model["landmarks68"].astype(np.int64)
        source = str(model["source"])

    tip = neutral[bosphorus_index[13]]   # "Nose tip"
    inside = (np.linalg.norm(neutral[faces] - tip, axis=2) <= crop_mm).all(axis=1)
    kept = faces[inside]
    used = np.unique(kept)
    remap = np.full(len(neutral), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    if (remap[bosphorus_index] < 0).any():
        raise ValueError(f"a Bosphorus landmark lies outside the {crop_mm} mm crop")

    rng = np.random.default_rng(PEOPLE_SEED)
    weights = rng.standard_normal((PEOPLE, identity_modes.shape[0]))
    people = np.tensordot(weights, identity_modes, axes=1)[:, used]

    shape_names = [s for shapes in AU_SHAPES.values() for s in shapes]
    shapes = np.stack([expression_modes[names.index(s)].astype(np.float64)[used] for s in shape_names])
    return dict(
        quantum_mm=np.float64(QUANTUM_MM),
        neutral=_quantise(neutral[used], "the neutral face"),
        faces=remap[kept].astype(np.uint16),
        people=_quantise(people, "a person's delta"),
        expression_names=np.array(shape_names),
        expressions=_quantise(shapes, "an expression shape"),
        au_names=np.array(list(AU_SHAPES)),
        au_shapes=np.array(["+".join(AU_SHAPES[au]) for au in AU_SHAPES]),
        bosphorus_index=remap[bosphorus_index].astype(np.int16),
        landmarks68=remap[landmarks68].astype(np.int16),
        crop_mm=np.float64(crop_mm),
        source=np.array(f"ICT FaceKit face model ({source}), MIT licence, Copyright (c) 2020 USC Institute "
                        f"for Creative Technologies; face area within {crop_mm:g} mm of the nose tip, "
                        f"{PEOPLE} people, {len(shape_names)} expression shapes"),
    )


def _write_atomic(path: Path, data: bytes) -> None:
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
        os.chmod(temporary, 0o644)   # package data: readable by everyone, as pip installs it
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="ICT FaceKit face_model.npz")
    parser.add_argument("--crop-mm", type=float, default=100.0)
    parser.add_argument("--out", type=Path, default=OUTPUT)
    args = parser.parse_args(argv)
    if not args.model.is_file():
        print(f"make_demo_faces: {args.model} not found (it lives in ../shared)", file=sys.stderr)
        return 2
    arrays = extract(args.model, args.crop_mm)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    _write_atomic(args.out, buffer.getvalue())
    licence = (args.model.parent / "LICENSE").read_bytes()
    header = ("ict_demo_faces.npz, the faces of tpscore's demo, is an extract of the\n"
              f"{arrays['source']}.\n"
              "It is distributed under the ICT FaceKit licence, reproduced below.\n\n").encode()
    _write_atomic(args.out.parent / LICENCE_OUTPUT.name, header + licence)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB: {len(arrays['neutral'])} vertices, "
          f"{len(arrays['faces'])} triangles, {len(arrays['people'])} people, "
          f"{len(arrays['expressions'])} expression shapes) and {LICENCE_OUTPUT.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
