"""The action-unit library: FACS action units as control points on the reference face,
the regions where they act, and the emotions.

Each action unit (AU) has muscle control points (along the fibres of the muscle that
makes it) and wrinkle control points (where the skin bulges or folds), a region of the
face (the upper or lower face, or a named region finer than those: the eyelids, the
nose and upper lip, ...) and a side for every point (left, right or centre), so that
an AU can be animated on one side only (``12L``). An emotion (``"happiness"``) and
``"all"`` are whole expressions (:class:`WholeExpression`): the whole motion a source's
scan shows, over the whole face; an emotion also has its recipe of AUs, which the
method as published animates. The library is data:
``tpscore/data/action_units.json`` (documented in the README); users load their own
with :meth:`ActionUnitLibrary.from_json` or add AUs with :meth:`ActionUnitLibrary.add`.

A control point's position is defined relative to the landmarks: a weighted mean of
named landmarks plus an (x, y) offset in mm in the reference frame; its depth is read
off the reference surface when the points are placed.
"""
from __future__ import annotations

import functools
import json
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

import numpy as np

from .._files import atomic_write
from .._validation import as_real
from ..face.landmarks import AnchoredPoint
from ..face.regions import HALVES, Region

__all__ = [
    "ControlPoint",
    "ActionUnit",
    "WholeExpression",
    "Activation",
    "ActionUnitLibrary",
    "default_library", "shipped_library",
    "REGIONS",
    "WHOLE_FACE",
    "ALL",
    "MAX_WEIGHT",
]

#: The region of a whole expression: every part of the face the scans show.
WHOLE_FACE = "face"
#: The request for the whole motion of any expressive scan.
ALL = "all"
#: The regions every library has; a library adds named ones (:class:`tpscore.face.regions.Region`).
REGIONS = (*HALVES, WHOLE_FACE)

#: The largest weight of an AU, and the largest transfer magnitude, in absolute value:
#: twice the modelled expression. [0, 1] is the expression's own range; values outside
#: it extrapolate (and warn); beyond this they make faces no expression makes (a weight
#: of 1e9 moved a face by metres).
MAX_WEIGHT = 2.0
_KINDS = ("muscle", "wrinkle")


@dataclass(frozen=True, kw_only=True)
class ControlPoint(AnchoredPoint):
    """One named control point of an AU: an anchored point of the muscle it follows
    (``kind="muscle"``) or of a fold the skin makes (``kind="wrinkle"``)."""

    kind: str

    def __post_init__(self):
        super().__post_init__()
        if self.kind not in _KINDS:
            raise ValueError(f"control point {self.name!r}: kind must be one of {_KINDS}, got {self.kind!r}")


@dataclass(frozen=True)
class ActionUnit:
    """A FACS action unit: its control points and the region of the face it moves."""

    code: str
    name: str
    region: str
    control_points: tuple[ControlPoint, ...]
    muscle: str = ""
    action: str = ""

    def __post_init__(self):
        if not re.fullmatch(r"[0-9A-Za-z_]+", self.code) or self.code[-1] in "LR":
            raise ValueError(f"AU code {self.code!r} must be alphanumeric and not end in L or R")
        if not isinstance(self.region, str) or not self.region:
            raise ValueError(f"AU {self.code}: region must be a region's name, got {self.region!r}")
        if len(self.control_points) < 1:
            raise ValueError(f"AU {self.code}: needs at least one control point")
        names = [p.name for p in self.control_points]
        if len(set(names)) != len(names):
            raise ValueError(f"AU {self.code}: control point names are not unique")
        object.__setattr__(self, "control_points", tuple(self.control_points))

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.control_points]

    def positions_xy(self, landmarks) -> np.ndarray:
        """(k, 2) control point positions for a face with these (22, 3) landmarks."""
        lm = np.asarray(landmarks, dtype=np.float64)
        return np.array([p.position_xy(lm) for p in self.control_points])

    def side_weights(self, side: str | None) -> np.ndarray:
        """Per-point weight of the motion: all 1 for both sides; for one side, 1 on that
        side, 0 on the other, and 0.5 on the midline (half of a centre point's motion
        belongs to each side)."""
        if side is None:
            return np.ones(len(self.control_points))
        keep = {"L": "left", "R": "right"}[side]
        return np.array([1.0 if p.side == keep else 0.5 if p.side == "centre" else 0.0
                         for p in self.control_points])

    def to_dict(self) -> dict:
        return {
            "code": self.code, "name": self.name, "region": self.region,
            "muscle": self.muscle, "action": self.action,
            "control_points": [
                {"name": p.name, "kind": p.kind, "side": p.side, "at": dict(p.at),
                 "offset_mm": list(p.offset_mm), **({"note": p.note} if p.note else {})}
                for p in self.control_points
            ],
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> "ActionUnit":
        try:
            points = tuple(
                ControlPoint(name=p["name"], kind=p["kind"], side=p["side"], at=p["at"],
                             offset_mm=tuple(p.get("offset_mm", (0.0, 0.0))), note=p.get("note", ""))
                for p in data["control_points"]
            )
            return cls(code=str(data["code"]), name=data["name"], region=data["region"],
                       control_points=points, muscle=data.get("muscle", ""),
                       action=data.get("action", ""))
        except KeyError as exc:
            raise ValueError(f"action unit entry lacks the field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class WholeExpression:
    """A whole expression: all the motion the source's expressive scan shows, over the
    whole face (``region`` is :data:`WHOLE_FACE`). ``name`` is an emotion's
    (``"happiness"``) or :data:`ALL`; ``recipe`` holds an emotion's AUs and weights
    (what the method as published animates), None for ``"all"``."""

    name: str
    recipe: Mapping[str, float] | None = None

    @property
    def region(self) -> str:
        return WHOLE_FACE

    @property
    def code(self) -> str:
        return self.name

    @property
    def control_points(self) -> tuple:
        return ()

    @property
    def names(self) -> list[str]:
        return []

    @property
    def bilateral(self) -> bool:
        """Whether it moves both sides alike: ``"all"`` is not known to; an emotion is
        when its recipe has no one-sided AU."""
        return self.recipe is not None and not any(code.strip().upper()[-1:] in ("L", "R") for code in self.recipe)

    def side_weights(self, side: str | None) -> np.ndarray:
        return np.ones(0)


@dataclass(frozen=True)
class Activation:
    """An AU (or a whole expression) at a weight, on both sides (side None) or one side
    ('L' or 'R')."""

    action_unit: ActionUnit | WholeExpression
    side: str | None = None
    weight: float = 1.0

    @property
    def whole(self) -> bool:
        """Whether it is a whole expression (:class:`WholeExpression`)."""
        return isinstance(self.action_unit, WholeExpression)

    @property
    def bilateral(self) -> bool:
        """Whether it moves both sides of the face alike."""
        return self.action_unit.bilateral if self.whole else self.side is None

    @property
    def label(self) -> str:
        if self.whole:
            return self.action_unit.name
        return f"AU{self.action_unit.code}{self.side or ''}"


@dataclass
class ActionUnitLibrary:
    """A set of action units, the named regions they act in and the emotion
    prototypes built from them."""

    action_units: dict[str, ActionUnit] = field(default_factory=dict)
    emotions: dict[str, dict[str, float]] = field(default_factory=dict)
    regions: dict[str, Region] = field(default_factory=dict)

    def _check_writable(self) -> None:
        if isinstance(self.action_units, MappingProxyType):
            raise ValueError("this is the shipped library that transfers share, and it is read-only: "
                             "tpscore.default_library() gives a library of your own to change")

    def __reduce__(self):
        # the shared read-only library pickles as a reference to itself
        if isinstance(self.action_units, MappingProxyType):
            return shipped_library, ()
        return super().__reduce__()

    @classmethod
    def from_json(cls, path) -> "ActionUnitLibrary":
        """Load a library from a JSON file in the format of the shipped one."""
        try:
            text = Path(path).read_text(encoding="utf-8")
            data = json.loads(text)
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: cannot read an action-unit library: {exc}") from None
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: Mapping, source: str = "library") -> "ActionUnitLibrary":
        if not isinstance(data, Mapping) or "action_units" not in data:
            raise ValueError(f"{source}: expected an object with an 'action_units' list")
        library = cls()
        for entry in data.get("regions", []):
            library.add_region(Region.from_dict(entry))
        for entry in data["action_units"]:
            library.add(ActionUnit.from_dict(entry))
        for name, recipe in data.get("emotions", {}).items():
            library.add_emotion(name, recipe)
        return library

    def to_json(self, path) -> None:
        doc = {"format": "tpscore-action-units", "version": 1,
               "regions": [region.to_dict() for region in self.regions.values()],
               "action_units": [au.to_dict() for au in self.action_units.values()],
               "emotions": self.emotions}
        atomic_write(path, json.dumps(doc, indent=1).encode("utf-8"))

    def add(self, action_unit: ActionUnit, *, replace: bool = False) -> None:
        self._check_writable()
        if action_unit.code in self.action_units and not replace:
            raise ValueError(f"AU {action_unit.code} is already in the library (pass replace=True)")
        if action_unit.region not in REGIONS and action_unit.region not in self.regions:
            raise ValueError(f"AU {action_unit.code}: unknown region {action_unit.region!r}; known: "
                             f"{', '.join([*REGIONS, *self.regions])} (add_region adds one)")
        self.action_units[action_unit.code] = action_unit

    def add_region(self, region: Region, *, replace: bool = False) -> None:
        """Add a named region (:class:`tpscore.face.regions.Region`) AUs can act in."""
        self._check_writable()
        if region.name in REGIONS:
            raise ValueError(f"region {region.name!r} is built in; choose another name")
        if region.name in self.regions and not replace:
            raise ValueError(f"region {region.name!r} is already in the library (pass replace=True)")
        self.regions[region.name] = region

    def add_emotion(self, name: str, recipe: Mapping[str, float]) -> None:
        """Register an emotion as weights over AU codes (with optional side, e.g. '12L')."""
        self._check_writable()
        recipe = {str(k): float(v) for k, v in recipe.items()}
        for code in recipe:
            self._split_code(code)  # raises for an unknown AU
        self.emotions[name.lower()] = recipe

    @property
    def codes(self) -> list[str]:
        return list(self.action_units)

    def __getitem__(self, code) -> ActionUnit:
        return self.action_units[self._split_code(str(code))[0]]

    def __contains__(self, code) -> bool:
        try:
            self._split_code(str(code))
        except ValueError:
            return False
        return True

    def _split_code(self, token: str) -> tuple[str, str | None]:
        token = token.strip().upper().removeprefix("AU")
        side = None
        if token and token[-1] in "LR" and token[:-1] in self.action_units:
            token, side = token[:-1], token[-1]
        if token not in self.action_units:
            raise ValueError(
                f"unknown action unit {token!r}; known: {', '.join(self.action_units)} "
                f"(add L or R for one side), or an emotion: {', '.join(self.emotions)}"
            )
        return token, side

    def parse(self, spec) -> list[Activation]:
        """Parse an AU request into activations.

        Accepts ``"12"``, ``"12L"``, ``"AU12R"``, several joined by ``,`` or ``+``
        (``"1,4,15"``), a weight after a colon (``"12:0.5"``), a mapping ``{"12": 1.0}``
        or a list of such tokens; or a whole expression: an emotion name
        (``"sadness"``) or ``"all"``, with an optional weight, alone (a whole
        expression already holds every AU its scan shows). Repeated AUs on the same side
        add their weights.
        """
        def weight_of(code, value) -> float:
            return as_real(value, f"action_units: the weight of {code!r}", low=-MAX_WEIGHT, high=MAX_WEIGHT)

        if isinstance(spec, Mapping):
            tokens = [(str(k), weight_of(k, v)) for k, v in spec.items()]
        else:
            # an AU code is text or a whole number; a float such as 2.5 or None is a slip
            if not isinstance(spec, (str, int, list, tuple)) or isinstance(spec, bool):
                raise ValueError(
                    "action_units must be an AU code ('12', '12L', '1,4,15', 'AU12:0.5'), an emotion "
                    f"name, a list of them or a mapping {{code: weight}}; got {spec!r:.80}")
            items = [spec] if isinstance(spec, (str, int)) else list(spec)
            tokens = []
            for item in items:
                if not isinstance(item, (str, int)) or isinstance(item, bool):
                    raise ValueError(f"action_units: {item!r:.80} is not an AU code (text or a whole number)")
                for part in re.split(r"[,+\s]+", str(item).strip()):
                    if not part:
                        continue
                    code, _, weight = part.partition(":")
                    if not weight:
                        tokens.append((code, 1.0))
                        continue
                    try:
                        number = float(weight)
                    except ValueError:
                        raise ValueError(f"bad weight in {part[:80]!r}: expected a number after ':'") from None
                    tokens.append((code, weight_of(code, number)))
        if not tokens:
            raise ValueError("no action unit given")
        wholes = [(code.strip().lower(), weight) for code, weight in tokens
                  if code.strip().lower() in self.emotions or code.strip().lower() == ALL]
        if wholes:
            if len(tokens) > 1:
                raise ValueError(
                    f"action_units: {wholes[0][0]!r} is a whole expression (all the motion its scan shows) and "
                    "cannot be combined with other AUs or expressions in one transfer")
            name, weight = wholes[0]
            recipe = None if name == ALL else dict(self.emotions[name])
            return [Activation(WholeExpression(name, recipe), None, weight)]
        merged: dict[tuple[str, str | None], float] = {}
        for code, weight in tokens:
            key = self._split_code(code)
            merged[key] = merged.get(key, 0.0) + weight
        for (code, side), weight in merged.items():
            if abs(weight) > MAX_WEIGHT:  # repeated codes add up
                raise ValueError(f"action_units: AU{code}{side or ''} adds up to a weight of {weight:g}, "
                                 f"outside [-{MAX_WEIGHT:g}, {MAX_WEIGHT:g}]")
        return [Activation(self.action_units[c], s, w) for (c, s), w in merged.items()]

    def recipe(self, activation: Activation) -> list[Activation]:
        """The AUs an activation stands for: itself for an AU, its recipe (scaled by its
        weight) for an emotion. ``"all"`` has no recipe: ValueError."""
        if not activation.whole:
            return [activation]
        if activation.action_unit.recipe is None:
            raise ValueError(f"{activation.label!r} carries the whole measured motion and has no recipe of action "
                             "units (the method as published needs AUs or an emotion)")
        return self.parse({code: weight * activation.weight for code, weight in activation.action_unit.recipe.items()})

    def region(self, name: str):
        """The named region (a :class:`tpscore.face.regions.Region`), or None for a half
        of the face or the whole face."""
        if name in REGIONS:
            return None
        try:
            return self.regions[name]
        except KeyError:
            raise ValueError(f"unknown region {name!r}; known: {', '.join([*REGIONS, *self.regions])}") from None


def default_library() -> ActionUnitLibrary:
    """The shipped library: every action unit of the Bosphorus database (AUs 1, 2, 4, 5,
    6, 7, 9, 10, 12, 14, 15, 16, 17, 18, 20, 22, 23, 24, 25, 26, 27, 28, 34, 43, 44),
    the regions they act in and the six emotions (and contempt). A new library each
    call, which the caller may change."""
    with resources.files("tpscore").joinpath("data/action_units.json").open("r", encoding="utf-8") as fh:
        return ActionUnitLibrary.from_dict(json.load(fh), source="action_units.json")


@functools.cache
def shipped_library() -> ActionUnitLibrary:
    """The shipped library read once and shared, read-only, by the functions that are
    given none (reading and checking it costs about 8 ms, a few percent of a transfer).
    A result keeps it (``TransferResult.model.library``); changing it raises a
    ValueError pointing to :func:`default_library`."""
    library = default_library()
    return ActionUnitLibrary(MappingProxyType(library.action_units), MappingProxyType(library.emotions),
                             MappingProxyType(library.regions))
