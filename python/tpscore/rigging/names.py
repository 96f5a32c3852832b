"""What a rig's morph targets are called: an expression's own name (``AU12``, ``AU12L``,
``AU1+AU4``, ``happiness``), or the ARKit blendshape it plays, with a bilateral AU cut
into its left and right halves where ARKit names the two sides apart.

The table (:data:`ARKIT_TABLE`) and the rules are described in docs/rig.md. The names
are planned from the expressions' names alone (:func:`plan_targets`); the weights that
cut a displacement into its parts come from the target face (:func:`part_weights`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..face.landmarks import landmark_index
from ..face.regions import smoothstep

__all__ = ["ARKIT_NAMES", "ARKIT_TABLE", "NAME_SCHEMES", "PlannedTarget", "plan_targets", "part_weights",
           "check_scheme", "MIDLINE_BAND_MM", "LIP_BAND_MM"]

#: The naming schemes a rig takes.
NAME_SCHEMES = ("au", "arkit")

#: ARKit's 52 face blendshapes (ARFaceAnchor.BlendShapeLocation), in Apple's order.
ARKIT_NAMES = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
    "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
    "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose",
    "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight",
    "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft",
    "mouthStretchRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
    "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)

#: AU code -> (ARKit name, rank). A name is one shape, or a pair ``(left, right)`` or,
#: for AU28, ``(upper, lower)`` that the AU's displacement is cut into. Where two AUs
#: play the same shape, the lower rank is the closer match and takes the name first
#: (AU26 the jaw drop over AU27 the mouth stretched open, AU24 the lip pressor over
#: AU23 the lip tightener, AU7 the lid tightener over AU44 the squint).
ARKIT_TABLE = {
    "1": ("browInnerUp", 0),
    "2": (("browOuterUpLeft", "browOuterUpRight"), 0),
    "4": (("browDownLeft", "browDownRight"), 0),
    "5": (("eyeWideLeft", "eyeWideRight"), 0),
    "6": (("cheekSquintLeft", "cheekSquintRight"), 0),
    "7": (("eyeSquintLeft", "eyeSquintRight"), 0),
    "44": (("eyeSquintLeft", "eyeSquintRight"), 1),
    "9": (("noseSneerLeft", "noseSneerRight"), 0),
    "10": (("mouthUpperUpLeft", "mouthUpperUpRight"), 0),
    "12": (("mouthSmileLeft", "mouthSmileRight"), 0),
    "14": (("mouthDimpleLeft", "mouthDimpleRight"), 0),
    "15": (("mouthFrownLeft", "mouthFrownRight"), 0),
    "16": (("mouthLowerDownLeft", "mouthLowerDownRight"), 0),
    "17": ("mouthShrugLower", 0),
    "18": ("mouthPucker", 0),
    "20": (("mouthStretchLeft", "mouthStretchRight"), 0),
    "22": ("mouthFunnel", 0),
    "24": (("mouthPressLeft", "mouthPressRight"), 0),
    "23": (("mouthPressLeft", "mouthPressRight"), 1),
    "26": ("jawOpen", 0),
    "27": ("jawOpen", 1),
    "28": (("mouthRollUpper", "mouthRollLower"), 0),
    "34": ("cheekPuff", 0),
    "43": (("eyeBlinkLeft", "eyeBlinkRight"), 0),
}

#: The width (mm, in the reference face's frame) of the band across the face's midline
#: over which a left half hands over to the right one: wide enough that the cut leaves
#: no crease where the motion crosses the midline (the inner brows, the lips), narrow
#: enough that each eye and mouth corner lies wholly on its own side.
MIDLINE_BAND_MM = 10.0
#: The same across the line between the lips, for the upper and the lower lip's halves.
LIP_BAND_MM = 4.0

_SINGLE_AU = re.compile(r"^AU([0-9A-Za-z_]+?)([LR]?)$")
_SIDES = ("left", "right")
_LIPS = ("upper", "lower")
_LIP_LINE = ("Left mouth corner", "Right mouth corner", "Upper lip inner middle", "Lower lip inner middle")


@dataclass(frozen=True)
class PlannedTarget:
    """One morph target: its name, the expression whose displacement it carries, and
    which part of it (None: the whole; ``left``/``right`` of the midline;
    ``upper``/``lower`` of the lips)."""

    name: str
    expression: str
    part: str | None = None


def check_scheme(names) -> str:
    if not isinstance(names, str) or names not in NAME_SCHEMES:
        raise ValueError(f"names must be one of {', '.join(map(repr, NAME_SCHEMES))}, got {names!r:.60}")
    return names


def plan_targets(expressions: Sequence[str], names: str = "au") -> list[PlannedTarget]:
    """The morph targets of a rig of these expressions (their own names: ``AU12``,
    ``AU12L``, ``AU1+AU4``, ``sadness``), in their order.

    With ``names="au"`` each expression is one target under its own name. With
    ``"arkit"`` an expression of one AU the table knows plays its ARKit shape: a
    bilateral AU with a left/right pair of names becomes two targets, its left and
    right halves; a one-sided AU (``AU12L``) takes its side's name; a one-sided AU whose
    shape has no sides keeps its own name. Where several expressions would play the
    same name, the closest match takes it (a one-sided scan before the half of a
    bilateral one, then the table's rank, then the order given), and the others keep
    their own names whole, so no motion is lost and no name is given twice. Emotions
    and combinations keep their names.
    """
    check_scheme(names)
    expressions = list(expressions)
    if len(set(expressions)) != len(expressions):
        raise ValueError(f"expressions repeat a name: {expressions}")
    if names == "au":
        return [PlannedTarget(e, e) for e in expressions]
    offers = {}
    for order, expression in enumerate(expressions):
        offer = _arkit_offer(expression)
        if offer is not None:
            priority, parts = offer
            offers[expression] = ((*priority, order), parts)
    taken: dict[str, list[PlannedTarget]] = {}
    claimed: set[str] = set()
    for expression, (_, parts) in sorted(offers.items(), key=lambda item: item[1][0]):
        wanted = [name for name, _ in parts]
        if claimed.isdisjoint(wanted):
            claimed.update(wanted)
            taken[expression] = [PlannedTarget(name, expression, part) for name, part in parts]
    planned = []
    for expression in expressions:
        planned += taken.get(expression, [PlannedTarget(expression, expression)])
    return planned


def _arkit_offer(expression: str):
    """((side rank, table rank), [(name, part), ...]) of an expression's ARKit shapes,
    or None when it has none."""
    match = _SINGLE_AU.match(expression)
    if not match or match.group(1) not in ARKIT_TABLE:
        return None
    code, side = match.groups()
    shape, rank = ARKIT_TABLE[code]
    if isinstance(shape, str):
        # a one-sided AU plays no shape that has no sides
        return None if side else ((1, rank), [(shape, None)])
    lips = code == "28"
    if side:
        if lips:
            return None
        return (0, rank), [(shape[0] if side == "L" else shape[1], None)]
    return (1, rank), list(zip(shape, _LIPS if lips else _SIDES))


def part_weights(part: str | None, points, landmarks) -> np.ndarray:
    """(n,) the share of each vertex's displacement that a part takes: 1 for the whole;
    for ``left`` (the subject's left, +x) a smooth step across the midline x = 0 of the
    reference frame, ``right`` its complement (so the halves add up to the whole); for
    ``upper`` a smooth step across the line between the lips (the mean height of the
    mouth corners and inner lip landmarks present; the whole without any), ``lower``
    its complement. `points` (n, 3) and `landmarks` (22, 3) are in the reference frame
    (a result's ``neutral_normalised`` and ``target.landmarks``)."""
    points = np.asarray(points, dtype=np.float64)
    if part is None:
        return np.ones(len(points))
    if part in _SIDES:
        left = smoothstep(-0.5 * MIDLINE_BAND_MM, 0.5 * MIDLINE_BAND_MM, points[:, 0])
        return left if part == "left" else 1.0 - left
    if part in _LIPS:
        lips = np.asarray(landmarks, dtype=np.float64)[[landmark_index(n) for n in _LIP_LINE]]
        lips = lips[np.isfinite(lips).all(axis=1)]
        if len(lips) == 0:
            # no landmark places the lips: the upper part takes the whole, the lower none
            return np.full(len(points), 1.0 if part == "upper" else 0.0)
        upper = smoothstep(-0.5 * LIP_BAND_MM, 0.5 * LIP_BAND_MM, points[:, 1] - lips[:, 1].mean())
        return upper if part == "upper" else 1.0 - upper
    raise ValueError(f"part must be None, 'left', 'right', 'upper' or 'lower', got {part!r}")
