"""Stability limits of the physical skin's integrators, measured.

For each step size the core runs a smile (AU12 at 0.5, ramped over 30 ms) and a jaw
opening (15 degrees) on the template head for 0.15 s of simulated time, without the
Python layer's safeguards (no sub-stepping, no retry), and the run counts as stable
when it neither diverges (a non-finite value, or a particle 100 mm from rest) nor
ends with a particle faster than 1 m/s. The semi-implicit integrator is swept in
multiples of ``SkinModel.stable_step`` (the estimate the Python layer clamps to); the
implicit one in milliseconds, on the template at its default step and above and on
the 5 mm template up to 20 ms (each implicit step is a sparse factorisation). The wall
time is per step run (a diverging run stops early).

    python benchmarks/skin_stability.py

Writes bench-output/skin_stability.md.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from tpscore.physics import SkinModel
from tpscore.physics.system import INTEGRATORS
from tpscore.showcase.datasets import skin_template
from report import write_report

ROOT = Path(__file__).resolve().parents[1]
SIMULATED_S = 0.15
CASES = (("smile", {"12": 0.5}, 0.0), ("jaw 15 deg", {}, 15.0))


def run(model, contractions, jaw_deg, integrator, dt):
    arrays = model.layers.arrays
    rest = model.layers.rest
    vector = model.contraction_vector(contractions)
    start = time.perf_counter()
    # the rest test (zero tolerances: it never stops the run) as often as SkinModel.simulate
    # makes it, so the wall time per step is a simulation's
    check_every = 1 if integrator == "implicit" else max(1, int(round(5e-4 / dt)))
    out = model._system.run(rest, np.zeros_like(rest), arrays.particle_foot, vector, math.radians(jaw_deg),
                            INTEGRATORS[integrator], dt, int(math.ceil(SIMULATED_S / dt)), 0.03, 0.0, 0.0, 3,
                            check_every, 100.0, 0, 0)
    seconds = time.perf_counter() - start
    velocities, steps, diverged = out[1], int(out[3]), out[5]
    speed = float(np.linalg.norm(velocities, axis=1).max()) if np.isfinite(velocities).all() else float("inf")
    stable = not diverged and speed < 1000.0
    # per step actually run: a diverging run stops early
    return stable, speed, seconds / max(steps, 1)


def sweep_cases(model, integrator, dt):
    """Each case of :data:`CASES` at one step: its table cell, and the wall time per
    step (s) of every run."""
    cells, per_step = [], []
    for _, units, jaw in CASES:
        contractions = model.head.contractions_for(units) if units else None
        stable, speed, seconds = run(model, contractions, jaw, integrator, dt)
        cells.append(("stable" if stable else "UNSTABLE") + f" (max speed {speed:.3g} mm/s)")
        per_step.append(seconds)
    return cells, per_step


def main() -> int:
    lines = ["| integrator | skin | step | smile | jaw 15 deg | wall time per step |", "|---|---|---:|---|---|---:|"]
    model = SkinModel(skin_template(2.5))
    limit = model.stable_step
    for factor in (0.5, 1.0, 1.25, 1.5, 1.75, 2.0, 3.0):
        dt = factor * limit
        cells, per_step = sweep_cases(model, "symplectic", dt)
        lines.append(f"| semi-implicit | template, 2,571 vertices | {dt * 1e6:.1f} us ({factor:g} x stable_step) | "
                     f"{cells[0]} | {cells[1]} | {1e3 * np.mean(per_step):.2f} ms |")
        print(lines[-1], flush=True)
    # the implicit step on the template itself, at its default step and above
    for dt in (2e-3, 5e-3):
        cells, per_step = sweep_cases(model, "implicit", dt)
        lines.append(f"| implicit | template, 2,571 vertices | {dt * 1e3:g} ms ({dt / limit:.0f} x stable_step) | "
                     f"{cells[0]} | {cells[1]} | {1e3 * np.mean(per_step):.1f} ms |")
        print(lines[-1], flush=True)
    coarse = SkinModel(skin_template(5.0))
    lines.append(f"| semi-implicit | template, 642 vertices | stable_step = {coarse.stable_step * 1e6:.1f} us | | | |")
    for dt in (1e-3, 2e-3, 5e-3, 1e-2, 2e-2):
        cells, per_step = sweep_cases(coarse, "implicit", dt)
        lines.append(f"| implicit | template, 642 vertices | {dt * 1e3:g} ms ({dt / coarse.stable_step:.0f} x "
                     f"stable_step) | {cells[0]} | {cells[1]} | {1e3 * np.mean(per_step):.1f} ms |")
        print(lines[-1], flush=True)
    text = "\n".join(lines)
    write_report(ROOT / "bench-output" / "skin_stability.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
