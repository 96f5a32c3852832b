"""Variants of the ICT FaceKit model for a stress test of expression transfer on people and
expression shapes that are not the model's own.

    python benchmarks/model_variants.py OUT_DIR

writes OUT_DIR/model_<variant>.npz in the model's own format, for
``../shared/tools/make_scans.py --model``:

- ``people``: other proportions (the face 0.93 as wide, 1.06 as tall and 1.08 as deep
  about the nose tip) and people 1.5 times as varied (the identity modes scaled); the
  expression shapes scaled with the face.
- ``shapes``: every expression shape's displacement multiplied by its own smooth gain
  over the face, exp(0.35 s(x)) with s a sum of six plane waves of 50-90 mm wavelength
  (unit variance): gains of 0.5-2, and the skin stretched by up to about a third more
  than the model's own shapes stretch it.
- ``gentle``: the same with exp(0.15 s(x)) and 80-140 mm waves: gains of 0.74-1.35.
- ``both``: ``people`` and ``shapes`` together.

These are the ICT model reshaped, not another face model: they show how far the transfer
leans on ICT's proportions and on how its expression shapes spread over the face. The
transfer never reads a model; make_scans.py writes scans of these as of ICT itself
(benchmarks/FIDELITY.md, "People and expression shapes that are not ICT's").
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from shared_data import shared_dir

#: The face's proportions in the ``people`` variant (x across, y up, z toward the viewer).
PROPORTIONS = np.array([0.93, 1.06, 1.08])
PEOPLE_SPREAD = 1.5
#: (seed, shortest and longest wavelength in mm, amplitude of s in the gain's exponent)
GAINS = {"shapes": (2026, 50.0, 90.0, 0.35), "gentle": (7, 80.0, 140.0, 0.15)}


def _gain_fields(points: np.ndarray, count: int, seed: int, shortest: float, longest: float,
                 amplitude: float) -> np.ndarray:
    """(count, n) smooth gains exp(amplitude s(x)), one field per expression shape."""
    rng = np.random.default_rng(seed)
    gains = np.empty((count, len(points)))
    for k in range(count):
        directions = rng.normal(size=(6, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        waves = directions * (2 * np.pi / rng.uniform(shortest, longest, size=(6, 1)))
        s = np.cos(points @ waves.T + rng.uniform(0, 2 * np.pi, 6)).sum(axis=1) / np.sqrt(3)
        gains[k] = np.exp(amplitude * s)
    return gains


def variants(model: dict) -> dict[str, dict]:
    neutral = model["neutral"].astype(np.float64)
    names = [str(name) for name in model["bosphorus_names"]]
    tip = neutral[model["bosphorus_index"][names.index("Nose tip")]]
    expressions = model["expression_modes"].astype(np.float64)
    shaped = {}
    for name, (seed, shortest, longest, amplitude) in GAINS.items():
        gains = _gain_fields(neutral - tip, len(expressions), seed, shortest, longest, amplitude)
        shaped[name] = expressions * gains[:, :, None]
    people = {"neutral": (neutral - tip) * PROPORTIONS + tip,
              "identity_modes": model["identity_modes"].astype(np.float64) * PROPORTIONS * PEOPLE_SPREAD}
    out = {
        "people": {**people, "expression_modes": expressions * PROPORTIONS},
        "shapes": {"expression_modes": shaped["shapes"]},
        "gentle": {"expression_modes": shaped["gentle"]},
        "both": {**people, "expression_modes": shaped["shapes"] * PROPORTIONS},
    }
    return {name: {**model, **{key: value.astype(np.float32) for key, value in changed.items()}}
            for name, changed in out.items()}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print(__doc__)
        return 2
    shared = shared_dir()
    if shared is None:
        print("model_variants.py needs ../shared (the ICT FaceKit model); not found")
        return 1
    model = dict(np.load(shared / "data" / "ict-facekit" / "face_model.npz", allow_pickle=False))
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    for name, variant in variants(model).items():
        np.savez(out / f"model_{name}.npz", **variant)
        print(out / f"model_{name}.npz")
    return 0


if __name__ == "__main__":
    sys.exit(main())
