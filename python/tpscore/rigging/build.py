"""A rig: every expression of a source person transferred onto one target person, as
the target's neutral face and one morph target per expression (or per half of one,
with ARKit's names), for any animation tool to open (:mod:`tpscore.rigging.gltf`,
:mod:`tpscore.rigging.usd`).

The source's neutral scan and the target are read and resampled once; each expression
is then one :func:`tpscore.transfer` on those grids.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np

from ..expression import ActionUnitLibrary, TransferOptions, TransferResult, transfer
from ..expression.action_units import shipped_library
from ..face.grid import DEFAULT_GRID_SHAPE, FaceGrid, _as_shape
from ..face.loading import load_scan, load_scans
from ..showcase.viewer import write_rig_html
from .names import check_scheme, part_weights, plan_targets
from .sources import source_scans

__all__ = ["MorphTarget", "Rig", "rig"]


@dataclass(frozen=True, eq=False)
class MorphTarget:
    """One morph target of a rig: its name, the expression it comes from, the part of
    that expression's displacement it carries (None: all of it; ``left``, ``right``,
    ``upper``, ``lower``: see :func:`tpscore.rigging.names.part_weights`), and that
    displacement at weight 1, (n, 3) mm in the target scan's frame at the rig's vertices."""

    name: str
    expression: str
    part: str | None
    displacement: np.ndarray


@dataclass(frozen=True, eq=False)
class Rig:
    """The target's neutral face and its morph targets, in the target scan's own frame
    (millimetres; +y up, the face toward +z, +x the subject's left).

    Attributes
    ----------
    results : dict
        {expression name: TransferResult}, the transfers the rig is made of, in order
        (names as ``AU12``, ``AU12L``, ``AU1+AU4``, ``sadness``).
    names : str
        ``"au"`` or ``"arkit"``: how the morph targets are named.
    targets : tuple of MorphTarget
    vertices : (n, 3) the target's valid grid vertices, neutral.
    triangles : (m, 3) indices into ``vertices``: one topology for every target.
    uv : (n, 2) each vertex's place in ``image`` (u right, v down).
    image : (h, w, 3) uint8 or None, the target's photograph.
    grid_index : (n,) each vertex's flat index on the target grid.
    """

    results: Mapping[str, TransferResult]
    names: str
    targets: tuple[MorphTarget, ...]
    vertices: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    image: np.ndarray | None
    grid_index: np.ndarray

    def __repr__(self) -> str:
        return (f"Rig({len(self.targets)} morph targets ({self.names} names) of {len(self.results)} expressions "
                f"on a face of {len(self.vertices)} vertices and {len(self.triangles)} triangles, "
                f"{'textured' if self.image is not None else 'no texture'})")

    @property
    def target_names(self) -> list[str]:
        return [t.name for t in self.targets]

    def write_html(self, path, *, title: str = "tpscore rig") -> None:
        """A self-contained page of the rig for any browser: the textured face with a
        slider per morph target (:func:`tpscore.showcase.viewer.write_rig_html`)."""
        textured = self.image is not None
        write_rig_html(path, self.vertices, [(t.name, t.displacement) for t in self.targets], self.triangles,
                       uv=self.uv if textured else None, image=self.image if textured else None, title=title,
                       subtitle=f"{len(self.targets)} morph targets; each slider moves the face on the GPU")

    def displacement(self, name: str) -> np.ndarray:
        """(n, 3) mm, the displacement of the morph target `name` at weight 1."""
        for target in self.targets:
            if target.name == name:
                return target.displacement
        raise ValueError(f"name: the rig has no morph target {name!r:.80}; it has {', '.join(self.target_names)}")

    @classmethod
    def from_results(cls, results: Mapping[str, TransferResult], names: str = "au") -> "Rig":
        """A rig of transfers onto one target: {expression name: TransferResult}, each
        at the magnitude its morph target has at weight 1. The names are expressions'
        as a transfer labels them (``AU12``, ``AU12L``, ``sadness``); the ARKit names are
        read from them (:func:`tpscore.rigging.names.plan_targets`).

        Raises
        ------
        ValueError
            Naming `results` (empty, not transfers, or onto different targets) or `names`.
        """
        check_scheme(names)
        results = _checked_results(results)
        first = next(iter(results.values()))
        index = np.flatnonzero(first.mask.reshape(-1))
        remap = np.full(first.mask.size, -1, dtype=np.int64)
        remap[index] = np.arange(len(index))
        targets = []
        for planned in plan_targets(list(results), names):
            result = results[planned.expression]
            field = result.field_in_scan().reshape(-1, 3)[index]
            share = part_weights(planned.part, result.neutral_normalised.reshape(-1, 3)[index],
                                 result.target.landmarks)
            targets.append(MorphTarget(planned.name, planned.expression, planned.part, field * share[:, None]))
        return cls(dict(results), names, tuple(targets),
                   np.ascontiguousarray(first.neutral.reshape(-1, 3)[index]), remap[_shared_triangles(results)],
                   np.ascontiguousarray(first.uv.reshape(-1, 2)[index]), first.image, index)


def _checked_results(results) -> dict[str, TransferResult]:
    if not isinstance(results, Mapping) or not results:
        raise ValueError(f"results must be a non-empty mapping {{expression name: TransferResult}}, "
                         f"got {type(results).__name__}")
    for key, result in results.items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"results: an expression's name must be text, got {key!r:.60}")
        if not isinstance(result, TransferResult):
            raise ValueError(f"results[{key!r}] must be a TransferResult, got {type(result).__name__}")
    first_name, first = next(iter(results.items()))
    for key, result in results.items():
        same = result.mask.shape == first.mask.shape and np.array_equal(result.mask, first.mask) and \
            np.allclose(result.neutral[result.mask], first.neutral[first.mask], rtol=0.0, atol=1e-6)
        if not same:
            raise ValueError(f"results: {key!r} and {first_name!r} were transferred onto different targets "
                             "(or grids); a rig is made on one target")
    return dict(results)


def _shared_triangles(results: Mapping[str, TransferResult]) -> np.ndarray:
    """The triangles (flat grid indices) of the rig's one topology.

    Every morph target moves the same mesh, and none may bridge an opening its
    expression cuts (an opened mouth, whose lips part). Each result already leaves out
    the triangles that straddle its own cut, so the mesh keeps the neutral target's
    triangles that every result keeps: the neutral face and the expressions that do not
    open the mouth lose those few triangles between the lips too, which shows as a seam
    where the lips meet, never as skin stretched across the opened mouth.
    """
    first = next(iter(results.values()))
    triangles = first.target.grid.triangles()
    n = first.mask.size  # at most 1024 x 1024, so a triangle's key stays within int64

    def key(t):
        return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]

    keys = key(triangles)
    keep = np.ones(len(triangles), dtype=bool)
    for result in results.values():
        keep &= np.isin(keys, key(result.triangles()))
    return triangles[keep]


Scan = FaceGrid | str | os.PathLike


def rig(source_neutral: Scan | None, expressions: Mapping[str, Scan] | str | os.PathLike, target: Scan, *,
        action_units: Sequence[str] | None = None, names: str = "au", grid=DEFAULT_GRID_SHAPE,
        options: TransferOptions = TransferOptions(), reference=None, library: ActionUnitLibrary | None = None,
        progress: Callable[[str], None] | None = None) -> Rig:
    """Transfer every expression of a source person onto a target, as a rig.

    Parameters
    ----------
    source_neutral : FaceGrid, str, path or None
        The source's neutral scan; None takes the neutral scan of the `expressions`
        folder.
    expressions : mapping or folder
        {AU request: expressive scan (path or FaceGrid)}: ``{"12": "smile.bnt",
        "sadness": "sad.bnt"}`` (requests as :func:`tpscore.transfer` takes them); or
        the source person's folder: ``bsNNN_<CODE>.bnt`` (the Bosphorus layout) or
        ``source_<name>.bnt`` (as ``tpscore demo`` writes into ``scans/``; see
        :mod:`tpscore.rigging.sources`). A folder's scans of no AU or emotion the library
        knows are left out.
    target : FaceGrid, str or path
        The target's neutral scan.
    action_units : sequence of str, optional
        Only these expressions (``["12", "AU4", "sadness"]``), in this order; default
        all, in the order given (a folder's: by file name).
    names : {"au", "arkit"}
        The morph targets' names: the expressions' (``AU12``, ``happiness``), or ARKit's
        blendshapes where one matches, a bilateral AU cut into its left and right
        halves (:func:`tpscore.rigging.names.plan_targets`; docs/rig.md has the table).
    grid : (H, W)
        The grid every scan given as a path is resampled on.
    options, reference, library
        As in :func:`tpscore.transfer`, for every transfer.
    progress : callable, optional
        Called with a short message as each step ends (the command line prints them).

    Returns
    -------
    Rig
        With the transfers in ``results``; write it with :func:`tpscore.rigging.write_gltf`.

    Raises
    ------
    ValueError
        Naming the argument: `expressions` (not a folder or mapping, a missing folder,
        no expressive scan, a request the library does not know), `action_units` (an
        unknown AU, or one no scan shows), `names`, `source_neutral` (None without a
        folder's neutral scan); a transfer's own errors name the face.
    """
    names = check_scheme(names)
    grid = _as_shape(grid, "grid")
    if library is not None and not isinstance(library, ActionUnitLibrary):
        raise ValueError(f"library must be an ActionUnitLibrary, got {type(library).__name__}")
    library = library or shipped_library()
    say = progress or (lambda message: None)
    began = time.perf_counter()
    neutral, scans = _expression_scans(source_neutral, expressions, library, say)
    chosen = _chosen(scans, action_units, library)
    neutral_grid, target_grid = _read([("source_neutral", neutral), ("target", target)], grid)
    say(f"read and resampled the source's neutral scan and the target ({time.perf_counter() - began:.2f} s)")
    results = {}
    for number, (name, (request, scan)) in enumerate(chosen.items(), 1):
        tag = f"{name} ({number}/{len(chosen)})"
        started = time.perf_counter()
        expressive = scan if isinstance(scan, FaceGrid) else load_scan(scan, shape=grid)
        results[name] = transfer(neutral_grid, expressive, target_grid, request, 1.0, reference=reference,
                                 library=library, options=options,
                                 progress=lambda message, tag=tag: say(f"{tag}: {message}"))
        say(f"{tag}: transferred ({time.perf_counter() - started:.2f} s)")
    made = Rig.from_results(results, names)
    say(f"made the rig: {len(made.targets)} morph targets on {len(made.vertices)} vertices "
        f"({time.perf_counter() - began:.2f} s in all)")
    return made


def _expression_scans(source_neutral, expressions, library, say):
    """(the source's neutral scan, {expression name: (request, scan)})."""
    if isinstance(expressions, Mapping):
        if source_neutral is None:
            raise ValueError("source_neutral: None takes the neutral scan of an expressions folder; "
                             "with a mapping of expressions, give the source's neutral scan")
        scans = {}
        for request, scan in expressions.items():
            if not isinstance(request, str):
                raise ValueError(f"expressions: a key must be an AU request (text such as '12' or "
                                 f"'sadness'), got {request!r:.60}")
            if not isinstance(scan, (FaceGrid, str, os.PathLike)):
                raise ValueError(f"expressions[{request!r}] must be a scan's path or a FaceGrid, "
                                 f"got {type(scan).__name__}")
            name = _expression_name(request, library, f"expressions[{request!r}]")
            if name in scans:
                raise ValueError(f"expressions: {scans[name][0]!r} and {request!r} are both {name}")
            scans[name] = (request, scan)
        if not scans:
            raise ValueError("expressions: the mapping is empty; a rig needs at least one expression")
        return source_neutral, scans
    folder = source_scans(expressions, "expressions")
    if source_neutral is None:
        if folder.neutral is None:
            raise ValueError(f"source_neutral: {folder.folder!r} has no neutral scan (bsNNN_N_N_0.bnt or "
                             "source_neutral.bnt); give the source's neutral scan")
        source_neutral = folder.neutral
    scans = {}
    for request, path in folder.items():
        try:
            name = _expression_name(request, library, "expressions")
        except ValueError:
            say(f"left out {os.path.basename(path)}: {request!r} is no AU or emotion the library knows")
            continue
        scans.setdefault(name, (request, path))
    if not scans:
        raise ValueError(f"expressions: no scan in {folder.folder!r} shows an AU or emotion the library knows")
    return source_neutral, scans


def _expression_name(request: str, library: ActionUnitLibrary, name: str) -> str:
    """An expression's name as its transfer labels it: ``AU12``, ``AU12L``, ``AU1+AU4``,
    ``sadness``."""
    try:
        return "+".join(activation.label for activation in library.parse(request))
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


def _chosen(scans: dict, action_units, library) -> dict:
    if action_units is None:
        return scans
    if isinstance(action_units, (str, bytes)) or not isinstance(action_units, Sequence) or not action_units:
        raise ValueError(f"action_units must be a non-empty list of AU requests (['12', 'sadness']), "
                         f"got {action_units!r:.60}")
    chosen = {}
    for wanted in action_units:
        if not isinstance(wanted, (str, int)) or isinstance(wanted, bool):
            raise ValueError(f"action_units: {wanted!r:.60} is not an AU request")
        name = _expression_name(str(wanted), library, "action_units")
        if name not in scans:
            raise ValueError(f"action_units: no source scan shows {name} (the scans show "
                             f"{', '.join(scans)})")
        chosen[name] = scans[name]
    return chosen


def _read(faces, shape) -> list[FaceGrid]:
    """The faces given as grids, and those given as paths read side by side."""
    for name, face in faces:
        if not isinstance(face, (FaceGrid, str, os.PathLike)):
            raise ValueError(f"{name} must be a FaceGrid or a scan's path, got {type(face).__name__}")
    paths = [face for _, face in faces if not isinstance(face, FaceGrid)]
    read = iter(load_scans(paths, shape=shape) if paths else [])
    return [face if isinstance(face, FaceGrid) else next(read) for _, face in faces]
