"""Simulating the skin: contractions and a jaw angle in, the settled skin and an
animation out.

:class:`SkinModel` builds a head's three layers once (:func:`~tpscore.physics.layers.build_layers`)
and the compiled system on them. :meth:`SkinModel.simulate` ramps the muscles and
the jaw smoothly from rest to their targets over ``ramp_time`` and steps until the
skin has settled (every particle slower than ``velocity_tolerance`` and its net force
below what would move it ``force_tolerance`` mm at rest, for a few steps running).

Two integrators:

- ``"symplectic"`` (default): semi-implicit (symplectic) Euler, v += dt f / m,
  x += dt v. Cheap steps and no numerical damping, but stable only below a step set by
  the stiffest spring: :attr:`SkinModel.stable_step` estimates it from the largest
  eigenvalues of M^-1 K (every spring at its stiff, beyond-the-knee slope, the contact
  penalty everywhere) and M^-1 D; a larger ``dt`` is cut into sub-steps with a
  warning, so any step a user picks runs stably.
- ``"implicit"``: linearised backward Euler; each step solves
  (M + dt D + dt^2 K) dv = dt (f - dt K v) with the core's sparse Cholesky (the
  pattern analysed once per model, the factor computed every step). Stable at large
  steps, but each step is a sparse factorisation: on the 2,571-vertex template it
  costs about 80 semi-implicit steps, and a smile settles some 15 times slower in
  wall time (see benchmarks/SKIN.md).

What is refused or clamped: contractions outside [0, 1] or for unknown muscles and a
jaw angle outside [0, 30] degrees raise ValueError; contractions that would invert
elements (a skin triangle flipping over, or a layer passing through the one under it)
are scaled down until none does, with a :class:`SkinWarning`; a run that diverges is
repeated at half the step (with a warning) and never returns NaN.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace
from typing import Mapping

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._validation import as_positive, check_options
from ..mesh import face_normals
from .head import Head
from .layers import SkinLayers, SkinMaterial, build_layers
from .linearised import prism_stiffness_matrix, spring_damping_matrix, spring_stiffness_matrix
from .system import INTEGRATORS

__all__ = ["SkinModel", "SimulationOptions", "SkinSimulation", "SkinWarning", "SimulationError", "MAX_JAW_DEG"]

#: The largest jaw angle accepted (degrees): a wide-open human mouth is about 30.
MAX_JAW_DEG = 30.0
# The explicit step limit is taken with this safety factor (the eigenvalue estimates
# are from below).
_STABILITY_SAFETY = 0.9
# Default implicit step (s): a fifteenth of the default ramp, twenty times the
# template's explicit limit.
_DEFAULT_IMPLICIT_DT = 2e-3
# Divergence: a particle farther than this from rest (mm) means the run blew up.
_DIVERGENCE_MM = 100.0
# Halvings of the step tried after a divergence before giving up.
_RETRIES = 3
# Scales tried, in turn, when the contractions invert elements.
_CLAMP_SCALES = (0.75, 0.5, 0.35, 0.25, 0.15, 0.1)


class SkinWarning(UserWarning):
    """A simulation changed what was asked (a smaller step, weaker contractions) or did
    not settle in the time allowed."""


class SimulationError(RuntimeError):
    """A simulation diverged even at the smallest step tried."""


@dataclass(frozen=True)
class SimulationOptions:
    """How :meth:`SkinModel.simulate` runs: the integrator, its step, the ramp, and when
    the skin counts as settled.

    Attributes
    ----------
    integrator : {"symplectic", "implicit"}
        Semi-implicit Euler (cheap steps, stable below :attr:`SkinModel.stable_step`) or
        linearised backward Euler (a sparse factorisation per step, stable at large
        steps); see the module notes.
    dt : float or None
        Step (s). None: :attr:`SkinModel.stable_step` semi-implicit, 2 ms implicit. A
        semi-implicit step above :attr:`SkinModel.stable_step` is split into stable
        sub-steps with a :class:`SkinWarning`.
    ramp_time : float
        Time (s) over which the contractions and the jaw rise smoothly (smoothstep) from
        rest to their targets; 0 applies them at once.
    max_time : float
        Simulated time (s) after which the run stops even if the skin has not settled
        (with a :class:`SkinWarning`).
    frames : int
        About how many animation frames to keep (>= 2), from rest to the settled skin.
    velocity_tolerance : float
        Rest: every particle slower than this (mm/s) ...
    force_tolerance : float
        ... and its net force (less what the skull bears) smaller than what would move
        it this far (mm) against its own stiffness at rest, for three tests running.
    """

    integrator: str = "symplectic"
    dt: float | None = None
    ramp_time: float = 0.03
    max_time: float = 0.5
    frames: int = 24
    velocity_tolerance: float = 1.0
    force_tolerance: float = 2e-3

    def __post_init__(self):
        check_options(self, positive=("max_time", "velocity_tolerance", "force_tolerance"),
                      non_negative=("ramp_time",), counts=(("frames", 2),),
                      choices={"integrator": tuple(INTEGRATORS)})
        if self.dt is not None:
            as_positive(self.dt, "SimulationOptions.dt")
            if self.dt > self.max_time:
                raise ValueError(f"SimulationOptions.dt ({self.dt:g} s) must not exceed max_time "
                                 f"({self.max_time:g} s)")


@dataclass(frozen=True, eq=False)
class SkinSimulation:
    """The result of :meth:`SkinModel.simulate`.

    Attributes
    ----------
    vertices : (n, 3) ndarray
        The settled skin (epidermis), mm, the head's vertex order.
    layers : (3n, 3) ndarray
        Every particle (epidermis, dermis, hypodermis).
    times : (k,) ndarray
        Simulated time (s) of each frame.
    frames : (k, n, 3) ndarray
        The skin at those times: an animation from rest to the settled state.
    contractions : dict
        The contractions applied (after any clamping).
    jaw_deg : float
        The jaw angle applied (after any clamping).
    scale : float
        1, or the factor the contractions and the jaw were scaled by to keep elements
        from inverting.
    settled : bool
        Whether the rest detector fired before ``max_time``.
    steps : int
    simulated_time : float
        Seconds of simulated time.
    dt : float
        The step used.
    integrator : str
    seconds : float
        Wall-clock time of the run(s).
    max_speed, max_residual : float
        At the last rest test: the largest particle speed (mm/s) and force residual (mm).
    """

    vertices: np.ndarray
    layers: np.ndarray
    times: np.ndarray
    frames: np.ndarray
    contractions: dict
    jaw_deg: float
    scale: float
    settled: bool
    steps: int
    simulated_time: float
    dt: float
    integrator: str
    seconds: float
    max_speed: float
    max_residual: float

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("inf")


def _largest_eigenvalue(matrix, masses: np.ndarray) -> float:
    """Largest eigenvalue of M^-1 A for symmetric A (3n x 3n) and masses (n,)."""
    scale = sp.diags(np.repeat(1.0 / np.sqrt(masses), 3))
    symmetric = (scale @ matrix @ scale).tocsr()
    symmetric.eliminate_zeros()
    if symmetric.nnz == 0:
        return 0.0  # e.g. no damping at all
    if symmetric.shape[0] <= 6:
        return float(np.linalg.eigvalsh(symmetric.toarray()).max())
    value = spla.eigsh(symmetric, k=1, which="LA", tol=1e-4, return_eigenvectors=False,
                       v0=np.ones(symmetric.shape[0]))
    return float(value[0])


class SkinModel:
    """The physical skin of a head, ready to simulate.

    Parameters
    ----------
    head : tpscore.physics.Head
        The skin mesh with its skull, regions, jaw and muscles.
    material : SkinMaterial
        The tissue's mechanical parameters (default: adult facial soft tissue).

    Examples
    --------
    >>> from tpscore import physics
    >>> model = physics.SkinModel(physics.load_template())
    >>> smile = model.simulate(model.head.contractions_for({"12": 0.6}))   # doctest: +SKIP
    >>> smile.vertices.shape                                               # doctest: +SKIP
    (2571, 3)
    """

    def __init__(self, head: Head, material: SkinMaterial = SkinMaterial()):
        if not isinstance(head, Head):
            raise ValueError(f"head must be a tpscore.physics.Head, got {type(head).__name__}")
        if not isinstance(material, SkinMaterial):
            raise ValueError(f"material must be a SkinMaterial, got {type(material).__name__}")
        self._head = head
        self._material = material
        self._layers: SkinLayers = build_layers(head, material)
        self._system = self._layers.arrays.core()
        self._stable_step: float | None = None
        # The skin's face normals and each column's direction at rest: the references
        # for telling an inverted element.
        n = len(head.vertices)
        rest = self._layers.rest
        self._rest_normals = face_normals(rest[:n], head.faces)
        self._column = rest[:n] - rest[2 * n:]
        self._column /= np.linalg.norm(self._column, axis=1, keepdims=True)

    @property
    def head(self):
        return self._head

    @property
    def material(self) -> SkinMaterial:
        return self._material

    @property
    def layers(self) -> SkinLayers:
        return self._layers

    @property
    def muscle_names(self) -> tuple:
        return self._layers.muscle_names

    @property
    def particles(self) -> int:
        return len(self._layers.rest)

    @property
    def stable_step(self) -> float:
        """Largest stable step (s) of the symplectic integrator, estimated.

        For a mode of frequency w with damping rate r the semi-implicit Euler step is
        stable for dt < (sqrt(r^2 + 4 w^2) - r) / w^2; w^2 is taken as the largest
        eigenvalue of M^-1 K with every spring at its stiff (beyond-the-knee) slope, the
        prisms' volume stiffness and the contact penalty on every particle, r as that of M^-1 D, and the result
        times 0.9.
        """
        if self._stable_step is None:
            # The matrices are assembled once per model, in NumPy: a setup cost next to
            # a simulation.
            arrays = self._layers.arrays
            stiff = replace(arrays, spring_stiffness=arrays.spring_stiffness_high)
            # with the contact penalty everywhere: any particle may touch the skull
            w2 = _largest_eigenvalue(spring_stiffness_matrix(stiff, self._layers.rest)
                                     + prism_stiffness_matrix(arrays, self._layers.rest) + self._contact_everywhere(),
                                     arrays.masses)
            r = _largest_eigenvalue(spring_damping_matrix(arrays, self._layers.rest), arrays.masses)
            self._stable_step = _STABILITY_SAFETY * (math.sqrt(r * r + 4.0 * w2) - r) / w2
        return self._stable_step

    def _contact_everywhere(self):
        arrays = self._layers.arrays
        normals = arrays.skull_normals[arrays.particle_foot]
        blocks = arrays.contact_stiffness[:, None, None] * np.einsum("si,sj->sij", normals, normals)
        n = len(blocks)
        rows = np.repeat(3 * np.arange(n), 9) + np.tile(np.repeat(np.arange(3), 3), n)
        cols = np.repeat(3 * np.arange(n), 9) + np.tile(np.tile(np.arange(3), 3), n)
        return sp.csr_matrix((blocks.reshape(-1), (rows, cols)), shape=(3 * n, 3 * n))

    # ------------------------------------------------------------------ inputs
    def contraction_vector(self, contractions) -> np.ndarray:
        """(k,) contractions in the model's muscle order from a mapping or an array."""
        names = self.muscle_names
        if contractions is None:
            return np.zeros(len(names))
        if isinstance(contractions, Mapping):
            vector = np.zeros(len(names))
            for name, value in contractions.items():
                if name not in names:
                    raise ValueError(f"contractions: unknown muscle {name!r}; known: {', '.join(names)}")
                try:
                    vector[names.index(name)] = float(value)
                except (TypeError, ValueError):
                    raise ValueError(f"contractions: the value for {name!r} must be a number, got {value!r}") from None
        else:
            try:
                vector = np.asarray(contractions, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"contractions must be a mapping muscle -> value or numbers: {exc}") from None
            if vector.shape != (len(names),):
                raise ValueError(f"contractions must have {len(names)} values (one per muscle), got {vector.shape}")
        if not np.isfinite(vector).all():
            raise ValueError("contractions contains NaN or infinite values")
        if np.any(vector < 0) or np.any(vector > 1):
            worst = names[int(np.argmax(np.abs(vector - np.clip(vector, 0, 1))))]
            raise ValueError(f"contractions must lie in [0, 1] (a fraction of each muscle's force; muscles only "
                             f"pull), got {vector[names.index(worst)]:g} for {worst!r}")
        return vector

    # ------------------------------------------------------------------ checks
    def inverted(self, positions: np.ndarray) -> int:
        """How many elements are inverted in (3n, 3) positions: skin triangles whose
        normal turned by more than 90 degrees from rest (folded over), and tissue
        columns whose skin particle passed below their hypodermal particle (along the
        column's rest direction). The dermal layer between them is highly deformable
        and may shear as far as it likes."""
        n = len(self._head.vertices)
        skin = positions[:n]
        normals = face_normals(skin, self._head.faces)
        folded = int(np.sum(np.einsum("ij,ij->i", normals, self._rest_normals) <= 0.0))
        crossed = int(np.sum(np.einsum("ij,ij->i", skin - positions[2 * n:], self._column) <= 0.0))
        return folded + crossed

    # ------------------------------------------------------------------ running
    def _run(self, vector, jaw_rad, options: SimulationOptions, dt, max_steps, record_every):
        rest = self._layers.rest
        zeros = np.zeros_like(rest)
        foot = self._layers.arrays.particle_foot
        # the rest test costs a force evaluation: every step for the implicit integrators,
        # about every half millisecond of simulated time for the cheap explicit steps
        check_every = 1 if options.integrator != "symplectic" else max(1, int(round(5e-4 / dt)))
        out = self._system.run(rest, zeros, foot, vector, jaw_rad, INTEGRATORS[options.integrator], dt,
                               int(max_steps), options.ramp_time, options.velocity_tolerance,
                               options.force_tolerance, 3, check_every, _DIVERGENCE_MM, int(record_every),
                               len(self._head.vertices))
        positions, _, _, steps, settled, diverged, sim_time, speed, residual, times, frames = out
        return dict(positions=positions, steps=int(steps), settled=bool(settled), diverged=bool(diverged),
                    time=float(sim_time), max_speed=float(speed), max_residual=float(residual), times=times,
                    frames=frames.reshape(len(times), len(self._head.vertices), 3))

    def simulate(self, contractions=None, jaw: float = 0.0, *,
                 options: SimulationOptions = SimulationOptions()) -> SkinSimulation:
        """Contract the muscles and open the jaw, and let the skin settle.

        Parameters
        ----------
        contractions : mapping muscle -> value, or (k,) array_like, optional
            Fractions of each muscle's force in [0, 1] (default: all relaxed). See
            :meth:`Head.contractions_for` for AU intensities.
        jaw : float
            Jaw opening angle (degrees) in [0, 30].
        options : SimulationOptions
            The integrator, its step, the ramp and the rest test.

        Returns
        -------
        SkinSimulation

        Raises
        ------
        ValueError
            For contractions, jaw or options out of range (the message names which).
        SimulationError
            If the run diverges even at an eighth of the step.
        """
        vector = self.contraction_vector(contractions)
        try:
            jaw_deg = float(jaw)
        except (TypeError, ValueError):
            raise ValueError(f"jaw must be an angle in degrees, got {jaw!r}") from None
        if not np.isfinite(jaw_deg) or not 0.0 <= jaw_deg <= MAX_JAW_DEG:
            raise ValueError(f"jaw must be an opening angle in [0, {MAX_JAW_DEG:g}] degrees, got {jaw!r}")
        if not isinstance(options, SimulationOptions):
            raise ValueError(f"options must be a SimulationOptions, got {type(options).__name__}")
        dt = options.dt
        if dt is None:
            dt = self.stable_step if options.integrator == "symplectic" else _DEFAULT_IMPLICIT_DT
        if options.integrator == "symplectic" and dt > self.stable_step:
            substeps = math.ceil(dt / self.stable_step)
            warnings.warn(f"dt = {dt:.3g} s is above the semi-implicit integrator's stable step "
                          f"({self.stable_step:.3g} s); stepping at dt / {substeps} = {dt / substeps:.3g} s",
                          SkinWarning, stacklevel=2)
            dt = dt / substeps

        start = time.perf_counter()
        scale = 1.0
        scales = iter(_CLAMP_SCALES)
        while True:
            result = self._settle(scale * vector, math.radians(scale * jaw_deg), options, dt)
            if self.inverted(result["positions"]) == 0:
                break
            try:
                scale = next(scales)
            except StopIteration:
                raise ValueError("contractions (and jaw): elements invert even at a tenth of the requested "
                                 "contractions; the muscle set or the head is faulty") from None
        if scale < 1.0:
            warnings.warn(f"contractions and jaw invert skin elements; scaled by {scale:g} to keep them upright",
                          SkinWarning, stacklevel=2)
        if not result["settled"]:
            warnings.warn(f"the skin did not settle within max_time = {options.max_time:g} s (largest speed "
                          f"{result['max_speed']:.3g} mm/s, force residual {result['max_residual']:.3g} mm); "
                          "the result is the last state", SkinWarning, stacklevel=2)
        seconds = time.perf_counter() - start
        positions = result["positions"]
        n = len(self._head.vertices)
        if not np.isfinite(positions).all():  # the run loop stops before this; a guard
            raise SimulationError("the simulation produced non-finite positions")
        used = {name: float(scale * v) for name, v in zip(self.muscle_names, vector) if v > 0}
        # The run records at a fixed interval without knowing when it will settle: keep
        # about `frames` of them, evenly spread, the first and the last included.
        keep = np.unique(np.round(np.linspace(0, len(result["times"]) - 1, options.frames)).astype(int))
        return SkinSimulation(
            vertices=positions[:n].copy(), layers=positions, times=result["times"][keep],
            frames=result["frames"][keep],
            contractions=used, jaw_deg=scale * jaw_deg, scale=scale, settled=result["settled"],
            steps=result["steps"], simulated_time=result["time"], dt=result["dt"], integrator=options.integrator,
            seconds=seconds, max_speed=result["max_speed"], max_residual=result["max_residual"])

    def _settle(self, vector, jaw_rad, options: SimulationOptions, dt: float):
        """One run, repeated at half the step while it diverges."""
        for attempt in range(_RETRIES + 1):
            max_steps = int(math.ceil(options.max_time / dt))
            expected = (options.ramp_time + 0.02) / dt
            record_every = max(1, int(round(expected / options.frames)))
            result = self._run(vector, jaw_rad, options, dt, max_steps, record_every)
            if not result["diverged"]:
                result["dt"] = dt
                return result
            if attempt < _RETRIES:
                warnings.warn(f"the simulation diverged at dt = {dt:.3g} s; repeating it at {dt / 2:.3g} s",
                              SkinWarning, stacklevel=3)
                dt = dt / 2
        raise SimulationError(f"the simulation diverged even at dt = {dt:.3g} s")
