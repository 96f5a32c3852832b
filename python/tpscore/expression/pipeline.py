"""Expression transfer in one call: model an AU on a source person, animate it on a
target person (docs/design.md, method 1).

The stages, one module each: normalisation of every face into the reference face's
frame (:mod:`tpscore.face.normalise`); the rigid alignment of the source's expressive
scan onto its neutral scan, and the source's motion (:mod:`tpscore.expression.modelling`,
with :mod:`~tpscore.expression.registration` and :mod:`~tpscore.expression.texture`); the
motion carried onto the target as one field per AU (:mod:`tpscore.expression.animation`).
"""
from __future__ import annotations

import os
import time
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cached_property, partial
from typing import Callable, Mapping

import numpy as np

from .._threads import blas_on_one_thread, helper_thread
from ..face.average_face import AverageFace, load_average_face
from ..face.grid import FaceGrid, GridMesh
from ..face.landmarks import MIN_LANDMARKS, N_LANDMARKS
from ..face.loading import load_scan
from ..face.normalise import NormalisedFace, kept_normalisation, normalise_face
from ..face.pose import check_landmarks
from ..face.regions import region_boundary
from .action_units import ActionUnitLibrary, shipped_library
from .animation import Animation, magnitude_weights
from .methods import transfer_method
from .modelling import ExpressionModel, coverage, mirror_plane
from .options import TransferOptions

__all__ = ["TransferResult", "transfer"]

#: A face as :func:`transfer` takes it: resampled, or the path of a scan to read.
Scan = FaceGrid | str | os.PathLike

_STAGE_MESSAGES = {"read": "read the source's scans", "normalise": "normalised the faces",
                   "align": "aligned the expressive scan", "model": "measured the source's motion",
                   "animate": "carried the motion onto the target"}


@dataclass(frozen=True)
class TransferResult:
    """The target wearing the expression, in the reference frame and in its scan frame.

    ``vertices``, ``neutral``, ``mask``, ``uv``, ``image`` and ``colours`` describe the
    animated target on its grid, in the target scan's own frame, with the target's own
    colours; ``animation`` gives any other magnitude. The frames are computed once, on
    first use (the result does not change: another magnitude is ``animation.frame(m)``).
    """

    animation: Animation
    magnitude: float | Mapping[str, float]
    model: ExpressionModel
    timings: dict = field(default_factory=dict)  # seconds per stage

    def __repr__(self) -> str:
        height, width = self.mask.shape
        if isinstance(self.magnitude, Mapping):
            amount = ", ".join(f"{k}={float(v):g}" for k, v in self.magnitude.items())
        else:
            amount = f"m={float(self.magnitude):g}"
        colour = "colour" if self.image is not None else "no colour"
        return (f"TransferResult({'+'.join(self.animation.labels)} at {amount} on a {height}x{width} target "
                f"({int(self.mask.sum())} valid vertices, {colour}), scan frame <- "
                f"{self.target.transform.method} normalisation, {sum(self.timings.values()):.2f} s)")

    @property
    def target(self) -> NormalisedFace:
        return self.animation.target

    @cached_property
    def vertices_normalised(self) -> np.ndarray:
        return self.animation.frame(self.magnitude)

    @cached_property
    def neutral_normalised(self) -> np.ndarray:
        return self.animation.frame(0.0)

    @cached_property
    def vertices(self) -> np.ndarray:
        """(H, W, 3) animated target in the target scan's own frame."""
        return self.animation.frame_in_scan(self.magnitude)

    @cached_property
    def neutral(self) -> np.ndarray:
        """(H, W, 3) the target grid it started from, in the target scan's own frame."""
        return self.animation.frame_in_scan(0.0)

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool, the target grid's valid vertices."""
        return self.target.grid.mask

    @property
    def uv(self) -> np.ndarray:
        """(H, W, 2) each target vertex's place in :attr:`image` (u right, v down)."""
        return self.target.grid.uv

    @property
    def image(self) -> np.ndarray | None:
        """The target scan's colour image (None for a scan without one)."""
        return self.target.grid.image

    @property
    def colours(self) -> np.ndarray | None:
        """(H, W, 3) float32 RGB in [0, 1]: the target's colour at each vertex, which the
        skin keeps as it moves (NaN where the mask is False); None without an image."""
        return self.target.grid.colours

    def triangles(self) -> np.ndarray:
        """(m, 3) the target grid's triangles (flat grid indices) without those that
        straddle an opened mouth (:meth:`Animation.triangles`)."""
        return self.animation.triangles()

    def mesh(self, magnitude=None) -> GridMesh:
        """The animated target as an indexed mesh in the target scan's frame (its valid
        vertices, the triangles of :meth:`triangles`, u,v): at the result's magnitude,
        or at another."""
        vertices = self.vertices if magnitude is None else self.animation.frame_in_scan(magnitude)
        grid = self.target.grid
        index = np.flatnonzero(grid.mask.reshape(-1))
        remap = np.full(grid.mask.size, -1, dtype=np.int64)
        remap[index] = np.arange(len(index))
        return GridMesh(np.ascontiguousarray(vertices.reshape(-1, 3)[index]), remap[self.triangles()],
                        np.ascontiguousarray(grid.uv.reshape(-1, 2)[index]), index)

    def field_in_scan(self) -> np.ndarray:
        """(H, W, 3) the displacement at the result's magnitude, in the target scan's
        frame (NaN where the mask is False). The animation is linear in the magnitude,
        so the target at a fraction t of it is ``neutral + t * field_in_scan()``."""
        return self.vertices - self.neutral

    def measured_motion(self) -> np.ndarray | None:
        """(H, W, 3) the source's measured displacement at each vertex of its neutral
        grid, in the reference frame (NaN off the mask): what the transfer carried.
        None for the method as published, which measures control points only (see
        ``model.motions``)."""
        if self.model.dense is None:
            return None
        grid = self.model.source.grid
        motion = np.full(grid.points.shape, np.nan)
        motion[grid.mask] = self.model.dense(grid.points[grid.mask])
        return motion

    def to_npz_dict(self) -> dict:
        """Arrays for ``--out result.npz`` (scan-frame arrays first, as scorers expect)."""
        to_normalised = self.target.transform
        scan_frame = self.target.grid.scan_frame
        if scan_frame is not None:
            to_normalised = scan_frame.inverse().then(to_normalised)
        return dict(
            vertices=self.vertices, neutral=self.neutral, mask=self.mask,
            vertices_normalised=self.vertices_normalised,
            neutral_normalised=self.neutral_normalised,
            scan_to_normalised=to_normalised.matrix,
            uv=self.target.grid.uv, landmarks=to_normalised.apply_inverse(self.target.landmarks),
            action_units=np.array(self.animation.labels),
        )


@blas_on_one_thread
def transfer(source_neutral: Scan, source_expressive: Scan, target: Scan, action_units,
             magnitude=1.0, *, reference=None, library: ActionUnitLibrary | None = None,
             options: TransferOptions = TransferOptions(),
             progress: Callable[[str], None] | None = None) -> TransferResult:
    """Put the source's expression on the target.

    Parameters
    ----------
    source_neutral, source_expressive, target : FaceGrid, str or path
        Resampled faces with landmarks (see :func:`tpscore.load_scan`); with their
        colour images, the source's motion follows its skin's texture. Or the paths of
        scans to read with :func:`tpscore.load_scan`'s defaults (landmarks and image
        beside each scan, a 150 x 150 grid): the source's two scans are then read side
        by side, and the target while the source's motion is measured.
    action_units : str, mapping or sequence
        What to transfer: ``"12"``, ``"12L"``, ``"1,4,15"``, ``{"12": 0.5}`` (see
        :meth:`ActionUnitLibrary.parse`), or a whole expression: an emotion's name
        (``"happiness"``, with the source's scan of that emotion) or ``"all"``, which
        carry all the motion the source's expressive scan shows.
    magnitude : float or mapping
        m in [0, 1], or a weight per field label; finite and within [-2, 2]
        (:data:`~tpscore.expression.action_units.MAX_WEIGHT`); outside [0, 1] it
        extrapolates the expression, with a warning.
    reference : AverageFace, optional
        The reference face (default: the one shipped with tpscore).
    library : ActionUnitLibrary, optional
        Default: the shipped library.
    options : TransferOptions
        Pipeline choices; ``TransferOptions.published()`` is the method as published.
    progress : callable, optional
        Called with a short message as each stage ends (the command line prints them;
        the modelling stage takes most of a transfer's time).

    Returns
    -------
    TransferResult
        With ``timings``, the seconds each stage took (``read``: reading the source's
        scans given as paths).

    Raises
    ------
    ValueError
        An argument of the wrong type or out of range (naming it), or a face whose
        landmarks do not allow a step (naming the face: ``source_neutral``,
        ``source_expressive`` or ``target``).
    """
    faces = {"source_neutral": source_neutral, "source_expressive": source_expressive, "target": target}
    _check_arguments(faces, options, reference, library)
    library = library or shipped_library()
    activations = library.parse(action_units)
    reference_face = (reference or load_average_face()).as_normalised_face()
    method = transfer_method(options, reference_face, library)
    labels = method.labels(activations)
    magnitude_weights(magnitude, labels)  # checked here, before the work, and only here
    clock = _Clock(progress)
    with helper_thread("tpscore-transfer") as second_thread:
        animation, model = _stages(method, activations, faces, second_thread, clock)
    return TransferResult(animation, magnitude, model, clock.timings)


def _check_arguments(faces: dict, options, reference, library) -> None:
    for name, face in faces.items():
        if not isinstance(face, (FaceGrid, str, os.PathLike)):
            raise ValueError(f"{name} must be a FaceGrid (read a scan with tpscore.load_scan) or a scan's "
                             f"path, got {type(face).__name__} {face!r:.60}")
    if not isinstance(options, TransferOptions):
        raise ValueError(f"options must be a TransferOptions (e.g. TransferOptions.published()), "
                         f"got {type(options).__name__} {options!r:.60}")
    if reference is not None and not isinstance(reference, AverageFace):
        raise ValueError(f"reference must be an AverageFace, got {type(reference).__name__}")
    if library is not None and not isinstance(library, ActionUnitLibrary):
        raise ValueError(f"library must be an ActionUnitLibrary, got {type(library).__name__}")
    for name, face in faces.items():
        if isinstance(face, FaceGrid):
            _check_face(name, face, options.check_landmarks)


class _Clock:
    """The seconds each stage took, and a progress message as each ends."""

    def __init__(self, progress):
        self.progress = progress
        self.timings = {}
        self._last = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings[stage] = now - self._last
        self._last = now
        if self.progress is not None and stage in _STAGE_MESSAGES:
            self.progress(f"{_STAGE_MESSAGES[stage]} ({self.timings[stage]:.2f} s)")


def _stages(method, activations, faces: dict, second_thread, clock: _Clock):
    """The transfer's stages in order on this thread; what depends on one face alone
    (reading the expressive scan and the target, the source's registration grid, the
    mirror planes) runs on the second thread ahead of use."""
    reference_landmarks = method.reference.landmarks
    clock.lap("setup")
    refuse = method.options.check_landmarks
    expressive_scan = second_thread.submit(_scan, "source_expressive", faces["source_expressive"], refuse)
    target_ready = second_thread.submit(_target_face, faces["target"], reference_landmarks, method.normalisation,
                                        refuse)
    neutral_grid = _scan("source_neutral", faces["source_neutral"], refuse)
    expressive_grid = expressive_scan.result()
    if not all(isinstance(face, FaceGrid) for face in faces.values()):
        clock.lap("read")
    with _naming("source_neutral"):
        neutral = _normalised(faces["source_neutral"], neutral_grid, reference_landmarks, method.normalisation)
    clock.lap("normalise")
    prepared = second_thread.submit(_prepare, method, neutral, target_ready, activations)
    mirrors = None
    if method.uses_mirror(activations):
        # needed once the source is registered; queued now so that the second thread fits
        # them as soon as it is free (waiting for the registration left it idle for a
        # third of the transfer, and the registration then shared its cores with them)
        mirrors = second_thread.submit(lambda: _mirror_planes((neutral, target_ready.result())))

    with _naming("source_expressive"):
        expressive = method.align(neutral, neutral_grid, expressive_grid, activations)
    clock.lap("align")
    target_face = target_ready.result()  # read by now; a bad target fails before the long stages
    model = method.model(neutral, expressive, activations)
    clock.lap("model")
    if model.texture is not None:
        # the texture tracking ran inside the modelling; report it as its own stage
        clock.timings["texture"] = model.texture.seconds
        clock.timings["model"] -= model.texture.seconds
    animation = method.animate(model, target_face)
    clock.lap("animate")
    prepared.result()
    if mirrors is not None:
        mirrors.result()
    return animation, model


def _scan(name: str, scan: Scan, refuse_landmarks: bool) -> FaceGrid:
    """The face itself, or the scan at its path read and checked."""
    if isinstance(scan, FaceGrid):
        return scan
    face = load_scan(scan)
    _check_face(name, face, refuse_landmarks)
    return face


def _target_face(target: Scan, reference_landmarks, normalisation: str, refuse_landmarks: bool) -> NormalisedFace:
    with _naming("target"):
        return _normalised(target, _scan("target", target, refuse_landmarks), reference_landmarks, normalisation)


def _normalised(given: Scan, grid: FaceGrid, reference_landmarks, normalisation: str) -> NormalisedFace:
    """A neutral face in the reference frame: once per FaceGrid the caller gave, with
    what later steps compute of it alone (:func:`kept_normalisation`), so that the next
    transfer from the same grids reuses it; afresh for a scan this transfer read."""
    if isinstance(given, FaceGrid):
        return kept_normalisation(grid, reference_landmarks, normalisation)
    return normalise_face(grid, reference_landmarks, normalisation)


def _prepare(method, neutral: NormalisedFace, target: Future, activations) -> None:
    """What the transfer needs of the two faces alone before the registration, kept with
    each face: what the method prepares of the source's neutral face, then, unless the
    mirror planes will be fitted (they include it), the target's surface. A ValueError
    is kept too, or raised again where the transfer uses the result, so errors and
    warnings come from the same step with or without this."""
    steps = [lambda: method.prepare(neutral)]
    if not method.uses_mirror(activations):
        steps.append(lambda: target.result().surface())
    _quietly(steps)


def _mirror_planes(faces) -> None:
    """Each face's mirror plane and coverage, kept with the face (see :func:`_prepare`)."""
    _quietly([partial(step, face) for face in faces for step in (mirror_plane, coverage)])


def _quietly(steps) -> None:
    for step in steps:
        try:
            step()
        except ValueError:
            pass


@contextmanager
def _naming(name: str):
    """Prefix the argument's name to a ValueError raised inside: a stage that works on
    one scan then says which of the three it was."""
    try:
        yield
    except ValueError as exc:
        if str(exc).startswith(name):
            raise
        try:
            named = type(exc)(f"{name}: {exc}")
        except TypeError:  # a subclass whose constructor takes other arguments
            named = ValueError(f"{name}: {exc}")
        raise named from None


def _check_face(name: str, face: FaceGrid, refuse_landmarks: bool = True) -> None:
    """Every face needs the landmarks of a landmark TPS and of the upper/lower split,
    landmarks that can be a face's (refused when they fit none, with
    ``refuse_landmarks``), and the canonical pose and unit."""
    present = int(np.isfinite(face.landmarks).all(axis=1).sum())
    if present < MIN_LANDMARKS:
        raise ValueError(f"{name}: only {present} of the {N_LANDMARKS} landmarks are present; a transfer "
                         f"needs at least {MIN_LANDMARKS} (give the scan's landmark file)")
    with _naming(name):
        region_boundary(face.landmarks)
    pose = check_landmarks(face.landmarks, f"{name}: the landmarks", refuse=refuse_landmarks)
    if pose is not None and pose.plausible and (
            pose.mm_per_unit != 1.0 or not np.array_equal(pose.rotation, np.eye(3))):
        # resample_scan brings scans into the canonical frame; this grid was built otherwise
        raise ValueError(
            f"{name}: the face {pose.describe()}; a transfer needs it frontal (looking toward +z, "
            "+y up) and in millimetres. tpscore.load_scan and resample_scan bring a scan there "
            "from its landmarks")
