"""Procedural 3D faces: neutral and expressive scans that need no external data.

The faces here feed the demo, the tests and the average face model (AFM). Each one is
a Bosphorus-like scan: a depth image on a regular x, y grid (rows from top to bottom =
decreasing y, columns = increasing x), in millimetres, looking toward +z, with +x the
subject's left and +y up, invalid pixels NaN, and the 22 Bosphorus landmarks.

The face surface
----------------
In the *face frame* the nose tip is at x = y = 0 and the neutral face is a height field
z = h(x, y), a sum of smooth terms whose sizes and places come from a
:class:`FaceParameters` (every length in mm):

* **base** -- the front of an ellipsoid whose half-width shrinks from the cheeks
  (``face_width``) to the jaw (``jaw_width``) below the mouth, so the lower face is
  V-shaped; ``face_depth`` sets how fast the sides curve back.
* **forehead** -- a broad bulge above the brows.
* **brow ridges** -- elongated bumps (``brow_prominence``) along each brow and a smaller
  one over the glabella between them.
* **eye sockets** -- wide hollows (``eye_depth``) around each eye with a smaller bump
  inside for the eyeball under the closed lids, and a shallow groove where the lids
  meet, from the inner to the outer eye corner.
* **nose** -- a ridge along the midline whose height grows from the nasion to the tip
  (``nose_projection``) and whose width grows from the bridge to the tip, a round tip,
  and the alae (nostril wings) at ``nose_width``.
* **cheeks** -- bumps (``cheek_fullness``) below and lateral to the eyes.
* **muzzle** -- the broad forward bulge of the teeth and jaws behind the lips.
* **lips** -- an upper and a lower bump (``lip_fullness``), a narrow groove along the
  closed mouth line between the mouth corners, a faint philtrum and the labiomental fold
  under the lower lip.
* **chin** -- a bump (``chin_prominence``) at the chin, and below the menton the surface
  falls away steeply toward the neck, as a frontal scanner sees it.

The scan covers an ellipse-ish face outline: from the forehead above the brows to just
below the chin, and as wide as the face (narrowing toward the jaw).

Landmarks
---------
The 22 Bosphorus landmarks have x, y positions that follow from the same parameters as
the surface (eye corners from ``eye_spacing`` and ``eye_width``, mouth corners from
``mouth_width``, and so on) and z = h(x, y): they lie on the surface by construction.

Action units
------------
Eight FACS action units are smooth 3D displacement fields d(X, Y) of the neutral skin,
in mm at full strength, placed relative to the landmarks so they follow the identity:

* **AU1** inner brow raiser (frontalis, medial part): the inner brows move up ~4 mm,
  with a long tail up the forehead and a short one down onto the upper lids.
* **AU2** outer brow raiser (frontalis, lateral part): the same over the outer brows.
* **AU4** brow lowerer (corrugator supercilii, depressor supercilii, procerus): the
  inner brows move down and toward the midline and bulge slightly forward.
* **AU12** lip corner puller (zygomaticus major): the mouth corners move up, out and
  back along the muscle toward the cheekbone; the cheeks rise and bulge forward.
* **AU14** dimpler (buccinator): the corners are tightened into the face and slightly
  out; a small dimple forms lateral to each corner.
* **AU15** lip corner depressor (depressor anguli oris): the corners and the skin below
  them move down.
* **AU17** chin raiser (mentalis): the chin boss moves up and forward and pushes the
  lower lip up.
* **AU20** lip stretcher (risorius with platysma): the corners are pulled laterally and a
  little down and back, stretching the lips.

Each field decays as a Gaussian (with different spreads above and below its centre where
the anatomy is lopsided), so an upper-face AU leaves the mouth still and a lower-face AU
leaves the brows still. One-sided versions (``"12L"``, ``"12R"``, and likewise for every
AU) multiply the two-sided field by a smooth step across the midline: ``"12L"`` moves
nothing at x <= -MIDLINE_RAMP_MM and ``"12L" + "12R" == "12"`` exactly. An expression
is a dict of AU weights, e.g. ``{"12": 1.0, "4L": 0.5}``; the displacement is linear in
the weights.

The expressive surface is the displaced neutral skin X + d(X), re-sampled as a height
field on the scan grid: for every grid x, y the skin point X whose displaced position
lands there is found by fixed-point iteration (the fields are gentle, their Jacobians
well below 1, so the iteration contracts). The same inversion handles an optional small
rigid pose. Landmarks move with the skin: landmark + d(landmark).
"""
from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field, fields
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from ..face.grid import FaceGrid
from ..face.landmarks import LANDMARK_NAMES
from ..face.regions import smoothstep
from ..face.resampling import resample_scan
from ..physics.head import Head, build_template

__all__ = [
    "FaceParameters",
    "face_point_cloud",
    "skin_template",
    "ExpressionMeshes",
    "ELASTIC_EXPRESSIONS",
    "elastic_faces",
    "afm_faces",
    "SyntheticScan",
    "ACTION_UNITS",
    "random_identity",
    "face_height",
    "face_landmarks",
    "au_displacement",
    "make_face",
    "sample_subjects",
    "embedded_faces",
    "demo_triplet",
]

#: The eight action units modelled, by FACS number.
ACTION_UNITS: tuple[str, ...] = ("1", "2", "4", "12", "14", "15", "17", "20")

#: Half-width (mm) of the smooth step across the midline that cuts a two-sided AU field
#: into its left and right halves.
MIDLINE_RAMP_MM = 4.0

# Scan-generation constants.
DEFAULT_SPACING_MM = 0.7
GRID_MARGIN_PIXELS = 2
# Fixed-point inversion of the displaced skin: the fields contract by well under a
# half per step, so 60 steps reach INVERSION_CONVERGED_MM (a pixel stops iterating
# there; heights then agree to ~1e-7 mm even on the steep sides of the nose); a pixel
# whose residual stays above INVERSION_TOLERANCE_MM is one the (posed) surface folds
# over, a scanner shadow.
INVERSION_MAX_STEPS = 60
INVERSION_CONVERGED_MM = 1e-8
INVERSION_TOLERANCE_MM = 1e-3
# Random holes: elliptical, semi-axes uniform in this range (mm).
HOLE_SEMI_AXIS_RANGE_MM = (2.0, 8.0)
# A posed scan is also shifted by up to this much (mm) along each axis.
POSE_MAX_TRANSLATION_MM = 5.0
# Relative spread of the random identities: a shared size factor, and each
# parameter's own variation (standard deviations), both cut at 2.5 sigma.
IDENTITY_SIZE_SD = 0.04
IDENTITY_PARAMETER_SD = 0.06
IDENTITY_CLIP_SD = 2.5
# The deterministic set of subjects (AFM, demo) and the demo's two identities.
EMBEDDED_SUBJECTS = 8
EMBEDDED_SEED = 2024
DEMO_SOURCE_SEED = 101
DEMO_TARGET_SEED = 202


@dataclass(frozen=True)
class FaceParameters:
    """Identity of a procedural face; every field is a length in mm.

    The defaults describe an average adult: outer eye corners 89 mm apart, inner
    37 mm, mouth corners 51 mm, nose tip ~28 mm in front of the cheeks and
    nasion-to-chin ~113 mm. Vertical positions are measured from the nose tip.
    """

    face_width: float = 130.0       #: width of the scanned face area at the cheeks
    face_depth: float = 62.0        #: depth semi-axis of the base ellipsoid
    jaw_width: float = 100.0        #: width of the face area at the jaw
    forehead_height: float = 38.0   #: scanned forehead above the middle of the brows
    eye_spacing: float = 63.0       #: distance between the eye centres
    eye_width: float = 26.0         #: inner to outer eye corner
    eye_height: float = 38.0        #: inner eye corners above the nose tip
    eye_depth: float = 11.0         #: depth of the eye sockets
    brow_height: float = 17.0       #: middle of the brows above the eye corners
    brow_prominence: float = 4.0    #: height of the brow ridges
    nose_length: float = 47.0       #: nasion above the nose tip
    nose_width: float = 34.0        #: alar width (between the nose peaks)
    nose_projection: float = 21.0   #: height of the nose ridge at the tip
    cheek_fullness: float = 5.0     #: height of the cheek bumps
    mouth_width: float = 51.0       #: distance between the mouth corners
    mouth_height: float = 30.0      #: mouth line below the nose tip
    upper_lip_height: float = 8.0   #: upper lip outer middle above the mouth line
    lower_lip_height: float = 9.0   #: lower lip outer middle below the mouth line
    lip_fullness: float = 4.0       #: height of the lip bumps
    chin_height: float = 28.0       #: chin middle below the mouth line
    chin_prominence: float = 8.0    #: height of the chin bump

    def __post_init__(self):
        for item in fields(self):
            value = getattr(self, item.name)
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"FaceParameters.{item.name} must be a number, got {value!r}") from None
            if not math.isfinite(number) or number <= 0:
                raise ValueError(f"FaceParameters.{item.name} must be finite and > 0, got {value!r}")
            object.__setattr__(self, item.name, number)
        if self.eye_width >= self.eye_spacing:
            raise ValueError(
                f"FaceParameters.eye_width ({self.eye_width}) must be smaller than "
                f"eye_spacing ({self.eye_spacing}) so the inner eye corners do not cross"
            )
        if self.mouth_width >= self.jaw_width or self.eye_spacing + self.eye_width >= self.face_width:
            raise ValueError("FaceParameters: the eyes and mouth must fit inside face_width and jaw_width")
        if self.eye_height >= self.nose_length:
            raise ValueError(
                f"FaceParameters.eye_height ({self.eye_height}) must be below the nasion "
                f"(nose_length {self.nose_length})"
            )

    def replace(self, **changes) -> "FaceParameters":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)


# Proportions and offsets (mm) that place anatomy not given by a FaceParameters field.
CANTHAL_TILT = 0.08              # outer eye corners above the inner, per mm of eye width
ALAR_LEVEL = -0.13               # nose peaks' height, as a fraction of the nose length
MENTON_DROP = 0.3                # menton below the chin middle, per mm of chin height
OUTLINE_BELOW_MENTON = 4.0       # the scan ends this far below the menton
BROW_INNER_END_INSET = 2.0       # inner brow end toward the midline from the inner corner
BROW_OUTER_END_OUTSET = 5.0      # outer brow end beyond the outer eye corner
BROW_INNER_END_DROP = 3.0        # brow ends below the brow's middle
BROW_OUTER_END_DROP = 4.0
NOSE_SADDLE_FRACTION = 0.5       # saddle points' x over the inner eye corners' x
NOSE_SADDLE_DROP = 4.0           # saddle points below the eye line


class _Anatomy:
    """Positions (face frame, mm) derived from FaceParameters: the anchors of the
    surface terms, the landmarks and the AU fields."""

    def __init__(self, p: FaceParameters):
        self.p = p
        self.x_eye_inner = (p.eye_spacing - p.eye_width) / 2
        self.x_eye_outer = (p.eye_spacing + p.eye_width) / 2
        self.x_eye = p.eye_spacing / 2
        self.y_eye = p.eye_height
        # The outer corners sit a little higher than the inner ones (canthal tilt).
        self.y_eye_outer = p.eye_height + CANTHAL_TILT * p.eye_width
        self.y_brow = p.eye_height + p.brow_height
        self.y_nasion = p.nose_length
        self.x_alar = p.nose_width / 2
        self.y_alar = ALAR_LEVEL * p.nose_length
        self.x_mouth = p.mouth_width / 2
        self.y_mouth = -p.mouth_height
        self.y_upper_lip = self.y_mouth + p.upper_lip_height
        self.y_lower_lip = self.y_mouth - p.lower_lip_height
        self.y_chin = self.y_mouth - p.chin_height
        # Menton (lowest point of the chin), below which the surface turns under.
        self.y_menton = self.y_chin - MENTON_DROP * p.chin_height
        self.y_top = self.y_brow + p.forehead_height
        self.y_bottom = self.y_menton - OUTLINE_BELOW_MENTON
        self.y_outline_centre = (self.y_top + self.y_bottom) / 2
        self.outline_half_height = (self.y_top - self.y_bottom) / 2

    # -- outline and base ellipsoid ------------------------------------------------
    def jaw_blend(self, y):
        """0 above the nose base, 1 at the chin and below: how jaw-like the width is."""
        return smoothstep(self.y_alar, self.y_chin, y)

    def outline_half_width(self, y):
        p = self.p
        return p.face_width / 2 + (p.jaw_width - p.face_width) / 2 * self.jaw_blend(y)

    def inside_outline(self, x, y):
        u = x / self.outline_half_width(y)
        v = (y - self.y_outline_centre) / self.outline_half_height
        return u * u + v * v <= 1.0

    def landmarks_xy(self) -> np.ndarray:
        """(22, 2) x, y of the landmarks, Bosphorus order."""
        brow_inner_x = self.x_eye_inner - BROW_INNER_END_INSET
        brow_outer_x = self.x_eye_outer + BROW_OUTER_END_OUTSET
        brow_inner_y = self.y_brow - BROW_INNER_END_DROP
        brow_outer_y = self.y_brow - BROW_OUTER_END_DROP
        saddle_x = NOSE_SADDLE_FRACTION * self.x_eye_inner
        saddle_y = self.y_eye - NOSE_SADDLE_DROP
        positions = {
            "Outer left eyebrow": (brow_outer_x, brow_outer_y),
            "Middle left eyebrow": (self.x_eye, self.y_brow),
            "Inner left eyebrow": (brow_inner_x, brow_inner_y),
            "Inner right eyebrow": (-brow_inner_x, brow_inner_y),
            "Middle right eyebrow": (-self.x_eye, self.y_brow),
            "Outer right eyebrow": (-brow_outer_x, brow_outer_y),
            "Outer left eye corner": (self.x_eye_outer, self.y_eye_outer),
            "Inner left eye corner": (self.x_eye_inner, self.y_eye),
            "Inner right eye corner": (-self.x_eye_inner, self.y_eye),
            "Outer right eye corner": (-self.x_eye_outer, self.y_eye_outer),
            "Nose saddle left": (saddle_x, saddle_y),
            "Nose saddle right": (-saddle_x, saddle_y),
            "Left nose peak": (self.x_alar, self.y_alar),
            "Nose tip": (0.0, 0.0),
            "Right nose peak": (-self.x_alar, self.y_alar),
            "Left mouth corner": (self.x_mouth, self.y_mouth),
            "Upper lip outer middle": (0.0, self.y_upper_lip),
            "Right mouth corner": (-self.x_mouth, self.y_mouth),
            "Upper lip inner middle": (0.0, self.y_mouth + MOUTH_LINE_HALF_GAP_MM),
            "Lower lip inner middle": (0.0, self.y_mouth - MOUTH_LINE_HALF_GAP_MM),
            "Lower lip outer middle": (0.0, self.y_lower_lip),
            "Chin middle": (0.0, self.y_chin),
        }
        return np.array([positions[name] for name in LANDMARK_NAMES], dtype=np.float64)


# Surface-term constants. Each is a shape choice of the model, named so the height
# function reads as anatomy. Lengths in mm; a SPREAD is the (x, y) standard deviation of
# a Gaussian term; an OFFSET is (lateral, vertical) from the anchor named in its comment.
BASE_WIDTH_FACTOR = 1.3          # base ellipsoid half-width over the outline half-width
BASE_HEIGHT_FACTOR = 1.5         # base ellipsoid half-height over the outline half-height
BASE_FLOOR = 0.05                # keeps the ellipsoid finite at grid corners outside it
FOREHEAD_BULGE_MM = 3.0
FOREHEAD_CENTRE_FRACTION = 0.8   # bulge centre above the brows, as a fraction of the forehead
FOREHEAD_SPREAD = (45.0, 25.0)
GLABELLA_FRACTION = 0.5          # glabella bump relative to the brow ridges
GLABELLA_DROP = 6.0              # glabella below the brow line
GLABELLA_SPREAD = (8.0, 7.0)
BROW_RIDGE_OFFSET = (2.0, -4.0)  # from the middle of the brow
BROW_RIDGE_SPREAD = (15.0, 6.0)
EYE_SOCKET_RAISE = 1.5           # socket centre above the eye line
EYE_SOCKET_WIDTH_FRACTION = 0.55  # x spread over the eye width
EYE_SOCKET_SPREAD_Y = 9.0
EYEBALL_FRACTION = 0.45          # eyeball bump relative to the socket depth
EYEBALL_RAISE = 0.8
EYEBALL_WIDTH_FRACTION = 0.33
EYEBALL_SPREAD_Y = 5.0
EYELID_LINE_DEPTH_MM = 1.2
EYELID_LINE_WIDTH_MM = 0.7
EYELID_LINE_ARCH_MM = 1.5        # the lid line bows up between the corners
NASION_FRACTION = 0.35           # nose ridge height at the nasion relative to the tip
NOSE_RIDGE_EXPONENT = 1.4        # >1: the ridge rises faster toward the tip (a straight dorsum)
NASION_FADE = 8.0                # spread of the ridge's fade above the nasion
COLUMELLA_FADE = 6.0             # spread of the ridge's fade below the tip
NOSE_BRIDGE_HALF_WIDTH = 5.0
NOSE_TIP_HALF_WIDTH = 8.0
NOSE_TIP_BULB_FRACTION = 0.18    # the round tip on top of the ridge
NOSE_TIP_BULB_DROP = 1.0
NOSE_TIP_BULB_SPREAD = (6.0, 5.0)
ALA_FRACTION = 0.32              # alae height relative to the nose projection
ALA_OFFSET = (-4.5, 1.0)         # from the nose peak landmark
ALA_SPREAD = (5.0, 5.5)
CHEEK_OFFSET = (6.0, 14.0)       # from the eye centre's x and the alar level
CHEEK_SPREAD = (16.0, 14.0)
MUZZLE_MM = 9.0
MUZZLE_RAISE = 2.0               # above the mouth line
MUZZLE_WIDTH_FRACTION = 0.5      # x spread over the mouth width
MUZZLE_SPREAD_Y = 16.0
UPPER_LIP_WIDTH_FRACTION = 0.36  # x spread over the mouth width
LOWER_LIP_WIDTH_FRACTION = 0.33
LIP_HEIGHT_FRACTION = 0.45       # y spread over the lip's height
LOWER_LIP_FULLNESS_RATIO = 1.1   # the lower lip is a little fuller than the upper
MOUTH_LINE_DEPTH_MM = 2.5
MOUTH_LINE_WIDTH_MM = 0.9
MOUTH_LINE_HALF_GAP_MM = 0.6     # inner lip landmarks above and below the mouth line
PHILTRUM_DEPTH_MM = 0.8
PHILTRUM_SPREAD = (2.5, 5.0)
LABIOMENTAL_DEPTH_MM = 2.5
LABIOMENTAL_DROP = 5.0           # fold below the lower lip outer middle
LABIOMENTAL_SPREAD = (14.0, 3.0)
CHIN_RAISE = 2.0                 # chin bump centre above the chin middle landmark
CHIN_SPREAD = (13.0, 9.0)
UNDER_CHIN_CURVATURE = 0.35      # how fast (1/mm) the surface turns under below the menton
UNDER_CHIN_KNEE = 3.0


def _gauss(x, y, cx, cy, sx, sy, sy_below=None):
    """exp(-((x-cx)^2/2sx^2 + (y-cy)^2/2sy^2)); below cy the spread is sy_below if given."""
    dx = (x - cx) / sx
    if sy_below is None:
        dy = (y - cy) / sy
    else:
        dy = (y - cy) / np.where(y >= cy, sy, sy_below)
    return np.exp(-0.5 * (dx * dx + dy * dy))


def _softplus(value, width):
    """A smooth max(value, 0) with a rounded knee `width` mm wide."""
    return width * np.logaddexp(0.0, value / width)


def _height(anatomy: _Anatomy, x, y):
    """Neutral surface z = h(x, y) in the face frame (mm)."""
    a, p = anatomy, anatomy.p
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    u = x / (a.outline_half_width(y) * BASE_WIDTH_FACTOR)
    v = (y - a.y_outline_centre) / (a.outline_half_height * BASE_HEIGHT_FACTOR)
    z = p.face_depth * (np.sqrt(np.maximum(1.0 - u * u - v * v, BASE_FLOOR)) - 1.0)

    z += FOREHEAD_BULGE_MM * _gauss(
        x, y, 0.0, a.y_brow + FOREHEAD_CENTRE_FRACTION * p.forehead_height, *FOREHEAD_SPREAD)
    z += GLABELLA_FRACTION * p.brow_prominence * _gauss(
        x, y, 0.0, a.y_brow - GLABELLA_DROP, *GLABELLA_SPREAD)
    for side in (1.0, -1.0):
        z += p.brow_prominence * _gauss(x, y, side * (a.x_eye + BROW_RIDGE_OFFSET[0]),
                                        a.y_brow + BROW_RIDGE_OFFSET[1], *BROW_RIDGE_SPREAD)
        z -= p.eye_depth * _gauss(x, y, side * a.x_eye, a.y_eye + EYE_SOCKET_RAISE,
                                  EYE_SOCKET_WIDTH_FRACTION * p.eye_width, EYE_SOCKET_SPREAD_Y)
        z += EYEBALL_FRACTION * p.eye_depth * _gauss(
            x, y, side * a.x_eye, a.y_eye + EYEBALL_RAISE,
            EYEBALL_WIDTH_FRACTION * p.eye_width, EYEBALL_SPREAD_Y)
        # The closed lids meet along a line from the inner to the outer eye corner.
        along = (side * x - a.x_eye_inner) / (a.x_eye_outer - a.x_eye_inner)
        lid_line_y = (a.y_eye + (a.y_eye_outer - a.y_eye) * along
                      + EYELID_LINE_ARCH_MM * along * (1.0 - along))
        lid_window = np.exp(-(((side * x - a.x_eye) / (0.5 * p.eye_width)) ** 6))
        z -= EYELID_LINE_DEPTH_MM * lid_window * np.exp(
            -0.5 * ((y - lid_line_y) / EYELID_LINE_WIDTH_MM) ** 2)
        z += ALA_FRACTION * p.nose_projection * _gauss(
            x, y, side * (a.x_alar + ALA_OFFSET[0]), a.y_alar + ALA_OFFSET[1], *ALA_SPREAD)
        z += p.cheek_fullness * _gauss(x, y, side * (a.x_eye + CHEEK_OFFSET[0]),
                                       a.y_alar + CHEEK_OFFSET[1], *CHEEK_SPREAD)

    # Nose ridge: height grows from the nasion to the tip, fades above the nasion and
    # quickly below the tip (the columella); the width grows toward the tip.
    t = np.clip((a.y_nasion - y) / a.y_nasion, 0.0, 1.0)
    ridge = p.nose_projection * (NASION_FRACTION + (1.0 - NASION_FRACTION) * t ** NOSE_RIDGE_EXPONENT)
    ridge = ridge * np.where(y > a.y_nasion, np.exp(-0.5 * ((y - a.y_nasion) / NASION_FADE) ** 2), 1.0)
    ridge = ridge * np.where(y < 0.0, np.exp(-0.5 * (y / COLUMELLA_FADE) ** 2), 1.0)
    half_width = NOSE_BRIDGE_HALF_WIDTH + (NOSE_TIP_HALF_WIDTH - NOSE_BRIDGE_HALF_WIDTH) * t
    z += ridge * np.exp(-0.5 * (x / half_width) ** 2)
    z += NOSE_TIP_BULB_FRACTION * p.nose_projection * _gauss(
        x, y, 0.0, -NOSE_TIP_BULB_DROP, *NOSE_TIP_BULB_SPREAD)

    # Mouth: muzzle, lips, closed mouth line, philtrum, labiomental fold.
    z += MUZZLE_MM * _gauss(x, y, 0.0, a.y_mouth + MUZZLE_RAISE,
                            MUZZLE_WIDTH_FRACTION * p.mouth_width, MUZZLE_SPREAD_Y)
    z += p.lip_fullness * _gauss(x, y, 0.0, a.y_mouth + 0.5 * p.upper_lip_height,
                                 UPPER_LIP_WIDTH_FRACTION * p.mouth_width,
                                 LIP_HEIGHT_FRACTION * p.upper_lip_height)
    z += LOWER_LIP_FULLNESS_RATIO * p.lip_fullness * _gauss(
        x, y, 0.0, a.y_mouth - 0.5 * p.lower_lip_height,
        LOWER_LIP_WIDTH_FRACTION * p.mouth_width, LIP_HEIGHT_FRACTION * p.lower_lip_height)
    line_window = np.exp(-((x / a.x_mouth) ** 6))
    z -= MOUTH_LINE_DEPTH_MM * line_window * np.exp(
        -0.5 * ((y - a.y_mouth) / MOUTH_LINE_WIDTH_MM) ** 2)
    z -= PHILTRUM_DEPTH_MM * _gauss(x, y, 0.0, 0.5 * (a.y_upper_lip + a.y_alar) - 1.0,
                                    *PHILTRUM_SPREAD)
    z -= LABIOMENTAL_DEPTH_MM * _gauss(x, y, 0.0, a.y_lower_lip - LABIOMENTAL_DROP,
                                       *LABIOMENTAL_SPREAD)

    z += p.chin_prominence * _gauss(x, y, 0.0, a.y_chin + CHIN_RAISE, *CHIN_SPREAD)
    z -= UNDER_CHIN_CURVATURE * _softplus(a.y_menton - y, UNDER_CHIN_KNEE) ** 2
    return z


# ----------------------------------------------------------------------------- AUs
# Amplitudes (mm at weight 1) and spreads (mm) of the AU fields. Directions are given
# for the subject's left side (x > 0); the right side is the mirror image.
BROW_RAISE_MM = 4.0
BROW_RAISE_BACK_FRACTION = 0.15  # the skin slides up a forehead that slopes back: -z with +y
INNER_BROW_RAISE_OFFSET = (-3.0, -3.0)   # from the inner eye corner's x and the brow line
OUTER_BROW_RAISE_OFFSET = (2.0, -2.0)    # from the outer eye corner's x and the brow line
BROW_RAISE_SPREAD_X = 10.0
BROW_RAISE_SPREAD_UP = 20.0      # the frontalis pulls a long strip of forehead skin
BROW_RAISE_SPREAD_DOWN = 7.0     # the upper lid skin follows only a little
BROW_LOWER_MM = np.array([-1.8, -3.0, 0.8])      # down, toward the midline, forward
BROW_LOWER_SPREAD = (10.0, 9.0)
BROW_LOWER_OFFSET = (-1.0, -3.0)         # from the inner eye corner's x and the brow line
LIP_PULL_MM = np.array([2.5, 4.0, -1.5])         # zygomaticus major: up, out, back
LIP_PULL_SPREAD = (11.0, 10.0)
CHEEK_RAISE_MM = np.array([0.5, 1.5, 1.5])       # the cheek bunches up and forward
CHEEK_RAISE_SPREAD = (12.0, 10.0)
CHEEK_RAISE_OFFSET = (8.0, 20.0)         # from the mouth corner
DIMPLER_MM = np.array([1.0, 0.3, -2.5])          # buccinator: into the face, slightly out
DIMPLER_SPREAD = (7.0, 7.0)
DIMPLE_DEPTH_MM = 1.5
DIMPLE_SPREAD = (4.0, 4.0)
DIMPLE_OFFSET = (8.0, -1.0)              # from the mouth corner
LIP_DEPRESS_MM = np.array([0.8, -4.0, -0.5])     # depressor anguli oris: down
LIP_DEPRESS_SPREAD = (9.0, 12.0)
LIP_DEPRESS_OFFSET = (1.0, -4.0)         # from the mouth corner: the muscle lies below it
CHIN_RAISE_MM = np.array([0.0, 3.5, 1.5])        # mentalis: chin boss up and forward
CHIN_RAISE_SPREAD = (13.0, 10.0)
CHIN_RAISE_ABOVE = 2.0                   # chin boss above the chin middle landmark
MENTALIS_HALF_SEPARATION = 5.0           # each half of the paired muscle off the midline
LOWER_LIP_PUSH_MM = np.array([0.0, 2.0, 1.5])    # the lower lip rides up on the chin
LOWER_LIP_PUSH_SPREAD = (14.0, 5.0)
LIP_STRETCH_MM = np.array([4.0, -0.5, -1.0])     # risorius: laterally
LIP_STRETCH_SPREAD = (12.0, 7.0)
LIP_STRETCH_OFFSET = (2.0, -1.0)         # from the mouth corner

_AU_PATTERN = re.compile(r"^(?:au)?\s*(\d+)\s*([lr]?)$", re.IGNORECASE)


def _parse_au(key) -> tuple[str, str]:
    """'AU12L', '12l', 12 -> ('12', 'L'); side '' for both sides."""
    match = _AU_PATTERN.match(str(key).strip())
    if match is None or match.group(1) not in ACTION_UNITS:
        raise ValueError(
            f"expression: unknown action unit {key!r}; known: "
            f"{', '.join(ACTION_UNITS)} (optionally with L or R for one side, e.g. '12L')"
        )
    return match.group(1), match.group(2).upper()


def _normalise_expression(expression) -> dict[str, float]:
    """Validate an expression dict and return it with canonical keys ('12', '12L')."""
    if expression is None:
        return {}
    if not isinstance(expression, dict):
        raise ValueError(f"expression must be a dict of AU weights, got {type(expression).__name__}")
    result: dict[str, float] = {}
    for key, weight in expression.items():
        number, side = _parse_au(key)
        try:
            value = float(weight)
        except (TypeError, ValueError):
            raise ValueError(f"expression[{key!r}] must be a number, got {weight!r}") from None
        if not math.isfinite(value):
            raise ValueError(f"expression[{key!r}] must be finite, got {weight!r}")
        name = number + side
        result[name] = result.get(name, 0.0) + value
    return result


def _side_field(amplitude, weights_xy, x_sign):
    """(3, ...) displacement: amplitude (3,) for the left side mirrored in x for the right."""
    return np.stack([x_sign * amplitude[0] * weights_xy,
                     amplitude[1] * weights_xy,
                     amplitude[2] * weights_xy])


def _au_field(anatomy: _Anatomy, au: str, x, y) -> np.ndarray:
    """Two-sided displacement (3, ...) of AU `au` at neutral skin positions x, y."""
    a = anatomy
    total = np.zeros((3,) + np.shape(x))
    for s in (1.0, -1.0):
        if au in ("1", "2"):
            if au == "1":
                anchor_x, (dx, dy) = a.x_eye_inner, INNER_BROW_RAISE_OFFSET
            else:
                anchor_x, (dx, dy) = a.x_eye_outer, OUTER_BROW_RAISE_OFFSET
            w = _gauss(x, y, s * (anchor_x + dx), a.y_brow + dy, BROW_RAISE_SPREAD_X,
                       BROW_RAISE_SPREAD_UP, BROW_RAISE_SPREAD_DOWN)
            lift = np.array([0.0, BROW_RAISE_MM, -BROW_RAISE_BACK_FRACTION * BROW_RAISE_MM])
            total += _side_field(lift, w, s)
        elif au == "4":
            w = _gauss(x, y, s * (a.x_eye_inner + BROW_LOWER_OFFSET[0]),
                       a.y_brow + BROW_LOWER_OFFSET[1], *BROW_LOWER_SPREAD)
            total += _side_field(BROW_LOWER_MM, w, s)
        elif au == "12":
            w = _gauss(x, y, s * a.x_mouth, a.y_mouth, *LIP_PULL_SPREAD)
            total += _side_field(LIP_PULL_MM, w, s)
            w = _gauss(x, y, s * (a.x_mouth + CHEEK_RAISE_OFFSET[0]),
                       a.y_mouth + CHEEK_RAISE_OFFSET[1], *CHEEK_RAISE_SPREAD)
            total += _side_field(CHEEK_RAISE_MM, w, s)
        elif au == "14":
            w = _gauss(x, y, s * a.x_mouth, a.y_mouth, *DIMPLER_SPREAD)
            total += _side_field(DIMPLER_MM, w, s)
            w = _gauss(x, y, s * (a.x_mouth + DIMPLE_OFFSET[0]), a.y_mouth + DIMPLE_OFFSET[1],
                       *DIMPLE_SPREAD)
            total += _side_field(np.array([0.0, 0.0, -DIMPLE_DEPTH_MM]), w, s)
        elif au == "15":
            w = _gauss(x, y, s * (a.x_mouth + LIP_DEPRESS_OFFSET[0]),
                       a.y_mouth + LIP_DEPRESS_OFFSET[1], *LIP_DEPRESS_SPREAD)
            total += _side_field(LIP_DEPRESS_MM, w, s)
        elif au == "17":
            # Mentalis is a paired muscle either side of the midline; each half lifts
            # the chin boss, so the two halves overlap on the midline.
            w = _gauss(x, y, s * MENTALIS_HALF_SEPARATION, a.y_chin + CHIN_RAISE_ABOVE,
                       *CHIN_RAISE_SPREAD)
            total += _side_field(0.5 * CHIN_RAISE_MM, w, s)
            w = _gauss(x, y, s * MENTALIS_HALF_SEPARATION, a.y_lower_lip, *LOWER_LIP_PUSH_SPREAD)
            total += _side_field(0.5 * LOWER_LIP_PUSH_MM, w, s)
        elif au == "20":
            w = _gauss(x, y, s * (a.x_mouth + LIP_STRETCH_OFFSET[0]),
                       a.y_mouth + LIP_STRETCH_OFFSET[1], *LIP_STRETCH_SPREAD)
            total += _side_field(LIP_STRETCH_MM, w, s)
        else:  # pragma: no cover - _parse_au rejects unknown AUs first
            raise ValueError(f"unknown action unit {au!r}")
    return total


def _side_window(side: str, x):
    """1 for both sides; for 'L'/'R' a smooth step across the midline (L + R == 1)."""
    if side == "":
        return 1.0
    left = smoothstep(-MIDLINE_RAMP_MM, MIDLINE_RAMP_MM, x)
    return left if side == "L" else 1.0 - left


def _displacement(anatomy: _Anatomy, expression: dict[str, float], x, y) -> np.ndarray:
    """(3, ...) displacement of the neutral skin at x, y for a canonical expression."""
    total = np.zeros((3,) + np.shape(x))
    for name, weight in expression.items():
        if weight == 0.0:
            continue
        number, side = _parse_au(name)
        total += weight * _au_field(anatomy, number, x, y) * _side_window(side, x)
    return total


# ---------------------------------------------------------------------------- public


def _as_identity(identity) -> FaceParameters:
    if identity is None:
        return FaceParameters()
    if isinstance(identity, FaceParameters):
        return identity
    if isinstance(identity, (int, np.integer)) and not isinstance(identity, bool):
        return random_identity(int(identity))
    raise ValueError(
        f"identity must be None, a FaceParameters or an int seed, got {type(identity).__name__}"
    )


def random_identity(seed: int) -> FaceParameters:
    """A plausible random adult face: the average with a shared size factor
    (sd 4 %) and each parameter varied on its own (sd 6 %), both cut at 2.5 sd.

    Deterministic given `seed`.
    """
    rng = np.random.default_rng(seed)
    base = FaceParameters()
    # A rare draw that breaks the parameters' consistency rules (say, the eye corners
    # above the nasion) is drawn again from the same stream: still deterministic.
    while True:
        size = 1.0 + IDENTITY_SIZE_SD * np.clip(rng.standard_normal(), -IDENTITY_CLIP_SD,
                                                IDENTITY_CLIP_SD)
        values = {}
        for item in fields(FaceParameters):
            own = IDENTITY_PARAMETER_SD * np.clip(rng.standard_normal(), -IDENTITY_CLIP_SD,
                                                  IDENTITY_CLIP_SD)
            values[item.name] = getattr(base, item.name) * size * (1.0 + own)
        try:
            return FaceParameters(**values)
        except ValueError:
            continue


def face_height(identity, x, y, expression=None) -> np.ndarray:
    """Height z (mm) of a face at x, y in its face frame (nose tip at x = y = 0).

    Without `expression` this is the neutral surface h(x, y); with one, the expressive
    surface: the height of the displaced skin found at x, y. Values outside the face
    outline are finite but meaningless.

    Parameters
    ----------
    identity : FaceParameters, int seed or None (the average face)
    x, y : array_like, broadcastable, mm
    expression : dict of AU weights, optional
    """
    anatomy = _Anatomy(_as_identity(identity))
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    expr = _normalise_expression(expression)
    if not expr:
        return _height(anatomy, x, y)
    skin_x, skin_y, _ = _invert_skin(anatomy, expr, np.eye(4), x, y)
    return _height(anatomy, skin_x, skin_y) + _displacement(anatomy, expr, skin_x, skin_y)[2]


def face_landmarks(identity, expression=None) -> np.ndarray:
    """The 22 landmarks (22, 3) in mm, face frame, Bosphorus order; they move with the skin."""
    anatomy = _Anatomy(_as_identity(identity))
    xy = anatomy.landmarks_xy()
    points = np.column_stack([xy, _height(anatomy, xy[:, 0], xy[:, 1])])
    expr = _normalise_expression(expression)
    if expr:
        points += _displacement(anatomy, expr, xy[:, 0], xy[:, 1]).T
    return points


def au_displacement(identity, expression, points_xy) -> np.ndarray:
    """Displacement (n, 3) in mm of the neutral skin at face-frame points (n, 2) (x, y).

    This is the ground truth of an expression: the neutral surface point
    (x, y, h(x, y)) moves to itself plus this vector.
    """
    anatomy = _Anatomy(_as_identity(identity))
    xy = np.asarray(points_xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"points_xy must have shape (n, 2), got {xy.shape}")
    return _displacement(anatomy, _normalise_expression(expression), xy[:, 0], xy[:, 1]).T.copy()


def _skin_to_scan(anatomy, expression, pose, skin_x, skin_y):
    """Scan-frame position (3, ...) of the skin point that is at skin_x, skin_y when neutral."""
    position = np.stack([skin_x, skin_y, _height(anatomy, skin_x, skin_y)])
    if expression:
        position = position + _displacement(anatomy, expression, skin_x, skin_y)
    return np.tensordot(pose[:3, :3], position, axes=1) + pose[:3, 3].reshape((3,) + (1,) * skin_x.ndim)


def _invert_skin(anatomy, expression, pose, x, y):
    """Neutral skin coordinates whose displaced, posed position lies at scan x, y.

    Returns skin_x, skin_y and the final residual (mm) per point. Fixed-point
    iteration with the in-plane part of the pose as the approximate Jacobian.
    """
    in_plane = pose[:2, :2]
    inverse = np.linalg.inv(in_plane)
    target = np.stack([x, y]).reshape(2, -1)
    skin = inverse @ (target - pose[:2, 3:4])
    residual = np.zeros(target.shape[1])
    if not expression and np.allclose(pose[:2, 2], 0.0):
        return skin[0].reshape(x.shape), skin[1].reshape(x.shape), residual.reshape(x.shape)
    active = np.arange(target.shape[1])
    for _ in range(INVERSION_MAX_STEPS):
        scan = _skin_to_scan(anatomy, expression, pose, skin[0, active], skin[1, active])[:2]
        error = target[:, active] - scan
        skin[:, active] += inverse @ error
        residual[active] = np.hypot(error[0], error[1])
        active = active[residual[active] > INVERSION_CONVERGED_MM]
        if active.size == 0:
            break
    return skin[0].reshape(x.shape), skin[1].reshape(x.shape), residual.reshape(x.shape)


@dataclass(frozen=True, eq=False)
class SyntheticScan:
    """A procedural Bosphorus-like scan and its ground truth.

    Attributes
    ----------
    points : (nrows, ncols, 3) float64
        Scan-frame x, y, z in mm; rows run top to bottom (decreasing y), columns left
        to right (increasing x); NaN at invalid pixels (background, holes, shadows).
    valid : (nrows, ncols) bool
    landmarks : (22, 3) float64
        Scan-frame landmarks in Bosphorus order (exact: no annotation error).
    spacing_mm : float
        Grid spacing.
    identity : FaceParameters
    expression : dict
        Canonical AU weights ({} for neutral).
    pose : (4, 4) float64
        Rigid transform from the face frame (nose tip at x = y = 0) to the scan frame.
    skin_xy : (nrows, ncols, 2) float64
        Ground-truth correspondence: the face-frame x, y each pixel's skin point has on
        the NEUTRAL face (NaN where invalid). Its neutral position is
        (x, y, face_height(identity, x, y)).
    clean_points : (nrows, ncols, 3) float64
        `points` before depth noise (NaN where invalid).
    """

    points: np.ndarray
    valid: np.ndarray
    landmarks: np.ndarray
    spacing_mm: float
    identity: FaceParameters
    expression: dict = field(default_factory=dict)
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    skin_xy: np.ndarray | None = None
    clean_points: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    def to_grid_points(self) -> np.ndarray:
        """A copy of `points` (nrows, ncols, 3) with NaN at invalid pixels."""
        return self.points.copy()

    def valid_points(self) -> np.ndarray:
        """The valid points as an (n, 3) array, row after row."""
        return self.points[self.valid]

    def uv(self) -> np.ndarray:
        """(nrows, ncols, 2) normalised image coordinates in [0, 1] (u across, v down)."""
        nrows, ncols = self.valid.shape
        rows, cols = np.mgrid[0:nrows, 0:ncols]
        return np.stack([(cols + 0.5) / ncols, (rows + 0.5) / nrows], axis=-1)

    def neutral_points(self) -> np.ndarray:
        """(nrows, ncols, 3) face-frame neutral position of each pixel's skin point."""
        x, y = self.skin_xy[..., 0], self.skin_xy[..., 1]
        anatomy = _Anatomy(self.identity)
        with np.errstate(invalid="ignore"):
            z = _height(anatomy, x, y)
        return np.stack([x, y, z], axis=-1)


def make_face(identity=None, expression=None, *, spacing_mm: float = DEFAULT_SPACING_MM,
              noise_mm: float = 0.0, holes: int = 0, pose_deg: float = 0.0,
              seed: int = 0) -> SyntheticScan:
    """Generate a procedural face scan.

    Parameters
    ----------
    identity : None, FaceParameters or int
        None is the average face; an int is a seed for :func:`random_identity`.
    expression : dict, optional
        AU weights, e.g. ``{"12": 1.0}`` or ``{"AU4": 0.5, "12L": 1.0}``; keys are the
        AUs in ``ACTION_UNITS`` optionally followed by L or R (subject's side).
    spacing_mm : float
        Grid spacing in mm (> 0). At 0.7 mm a face has about 33k valid points.
    noise_mm : float
        Standard deviation of Gaussian depth (z) noise added to valid points.
    holes : int
        Number of random elliptical holes (semi-axes 2-8 mm) cut into the face.
    pose_deg : float
        Largest random rotation about each axis (roll half of it), about the nose tip,
        with a random shift of up to 5 mm per axis; 0 keeps the face frame.
    seed : int
        Seed for the noise, holes and pose (independent streams).

    Returns
    -------
    SyntheticScan
    """
    params = _as_identity(identity)
    expr = _normalise_expression(expression)
    try:
        spacing = float(spacing_mm)
    except (TypeError, ValueError):
        raise ValueError(f"spacing_mm must be a number, got {spacing_mm!r}") from None
    if not math.isfinite(spacing) or spacing <= 0:
        raise ValueError(f"spacing_mm must be finite and > 0, got {spacing_mm!r}")
    if spacing < 0.1:
        raise ValueError(f"spacing_mm must be >= 0.1 mm (finer grids are huge), got {spacing_mm!r}")
    noise = float(noise_mm)
    if not math.isfinite(noise) or noise < 0:
        raise ValueError(f"noise_mm must be finite and >= 0, got {noise_mm!r}")
    if isinstance(holes, bool) or not isinstance(holes, (int, np.integer)) or holes < 0:
        raise ValueError(f"holes must be an integer >= 0, got {holes!r}")
    pose_limit = float(pose_deg)
    if not math.isfinite(pose_limit) or not 0 <= pose_limit <= 30:
        raise ValueError(f"pose_deg must be in [0, 30] degrees, got {pose_deg!r}")

    anatomy = _Anatomy(params)
    pose_rng, noise_rng, hole_rng = (np.random.default_rng(s)
                                     for s in np.random.SeedSequence(seed).spawn(3))
    pose = np.eye(4)
    if pose_limit > 0:
        yaw, pitch = pose_rng.uniform(-pose_limit, pose_limit, size=2)
        roll = pose_rng.uniform(-pose_limit / 2, pose_limit / 2)
        # R = Ry(yaw) Rx(pitch) Rz(roll): intrinsic y, x', z'' angles
        rotation = Rotation.from_euler("YXZ", [yaw, pitch, roll], degrees=True).as_matrix()
        pivot = np.array([0.0, 0.0, float(_height(anatomy, 0.0, 0.0))])
        shift = pose_rng.uniform(-POSE_MAX_TRANSLATION_MM, POSE_MAX_TRANSLATION_MM, size=3)
        pose[:3, :3] = rotation
        pose[:3, 3] = pivot + shift - rotation @ pivot

    # Grid extent: the posed, displaced outline plus a margin, on multiples of spacing.
    angle = np.linspace(0.0, 2.0 * np.pi, 721)
    outline_y = anatomy.y_outline_centre + anatomy.outline_half_height * np.sin(angle)
    outline_x = anatomy.outline_half_width(outline_y) * np.cos(angle)
    outline = _skin_to_scan(anatomy, expr, pose, outline_x, outline_y)
    margin = GRID_MARGIN_PIXELS * spacing
    x0 = np.floor((outline[0].min() - margin) / spacing) * spacing
    y_top = np.ceil((outline[1].max() + margin) / spacing) * spacing
    ncols = int(np.ceil((outline[0].max() + margin - x0) / spacing)) + 1
    nrows = int(np.ceil((y_top - (outline[1].min() - margin)) / spacing)) + 1
    grid_x = x0 + spacing * np.arange(ncols)
    grid_y = y_top - spacing * np.arange(nrows)
    x, y = np.meshgrid(grid_x, grid_y)

    skin_x, skin_y, residual = _invert_skin(anatomy, expr, pose, x, y)
    valid = anatomy.inside_outline(skin_x, skin_y) & (residual < INVERSION_TOLERANCE_MM)
    z = _skin_to_scan(anatomy, expr, pose, skin_x, skin_y)[2]

    if holes:
        rows, cols = np.nonzero(valid)
        for _ in range(holes):
            pick = hole_rng.integers(len(rows))
            cx, cy = grid_x[cols[pick]], grid_y[rows[pick]]
            semi_a, semi_b = hole_rng.uniform(*HOLE_SEMI_AXIS_RANGE_MM, size=2)
            theta = hole_rng.uniform(0.0, np.pi)
            du = (x - cx) * np.cos(theta) + (y - cy) * np.sin(theta)
            dv = -(x - cx) * np.sin(theta) + (y - cy) * np.cos(theta)
            valid &= (du / semi_a) ** 2 + (dv / semi_b) ** 2 > 1.0

    clean = np.stack([x, y, z], axis=-1)
    clean[~valid] = np.nan
    points = clean.copy()
    if noise > 0:
        points[..., 2] += noise * noise_rng.standard_normal(valid.shape)
        points[~valid] = np.nan
    skin_xy = np.stack([skin_x, skin_y], axis=-1)
    skin_xy[~valid] = np.nan

    landmarks = face_landmarks(params, expr) @ pose[:3, :3].T + pose[:3, 3]
    return SyntheticScan(points=points, valid=valid, landmarks=landmarks, spacing_mm=spacing,
                         identity=params, expression=expr, pose=pose, skin_xy=skin_xy,
                         clean_points=clean)


def sample_subjects(n: int = EMBEDDED_SUBJECTS, seed: int = EMBEDDED_SEED) -> list[FaceParameters]:
    """`n` deterministic random identities (the average face first when seed is the default).

    The default set of 8 is the one the average face model and the demo use.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    seeds = np.random.SeedSequence(seed).generate_state(max(int(n), 1))[: int(n)]
    return [random_identity(int(s)) for s in seeds]


def embedded_faces(n: int = EMBEDDED_SUBJECTS, *, spacing_mm: float = DEFAULT_SPACING_MM,
                   seed: int = EMBEDDED_SEED) -> list[SyntheticScan]:
    """Neutral, clean scans of the deterministic subjects of :func:`sample_subjects`."""
    return [make_face(params, spacing_mm=spacing_mm) for params in sample_subjects(n, seed)]


def demo_triplet(au="12", magnitude: float = 1.0, *, spacing_mm: float = DEFAULT_SPACING_MM,
                 noise_mm: float = 0.0, holes: int = 0, pose_deg: float = 0.0,
                 seed: int = 0) -> tuple[SyntheticScan, SyntheticScan, SyntheticScan]:
    """(source neutral, source expressive, target neutral) scans for a transfer demo.

    `au` is an AU key ("12", "4", "12L", ...) or a whole expression dict; `magnitude`
    scales it. Source and target are two fixed identities outside the embedded set.
    """
    expression = au if isinstance(au, dict) else {au: 1.0}
    expression = {key: float(magnitude) * float(value)
                  for key, value in _normalise_expression(expression).items()}
    options = dict(spacing_mm=spacing_mm, noise_mm=noise_mm, holes=holes, pose_deg=pose_deg)
    source = random_identity(DEMO_SOURCE_SEED)
    target = random_identity(DEMO_TARGET_SEED)
    return (make_face(source, None, seed=seed, **options),
            make_face(source, expression, seed=seed + 1, **options),
            make_face(target, None, seed=seed + 2, **options))


def skin_template(spacing_mm: float = 2.5, *, muscles=None) -> Head:
    """The physical skin's template head (:func:`tpscore.physics.build_template`) made
    from the procedural average face at ``spacing_mm``: 2.5 mm gives the shipped
    ``skin_template.npz`` (about 2,600 vertices), 1.25 mm about 10,000."""
    return build_template(make_face(None, spacing_mm=spacing_mm), spacing_mm, muscles=muscles)


#: The expressions of :func:`elastic_faces`: a name and its AU weights.
ELASTIC_EXPRESSIONS = {"smile": {"12": 1.0}, "frown": {"4": 1.0}, "brows": {"1": 1.0, "2": 1.0},
                       "dimpler": {"14": 1.0}, "sad_mouth": {"15": 1.0, "17": 0.5}, "stretch": {"20": 1.0}}


class ExpressionMeshes(NamedTuple):
    """A procedural face as a mesh, and its expressions on the same vertices.

    Attributes
    ----------
    neutral : (n, 3) float64, mm, the face frame
    faces : (m, 3) int64
    landmarks : (22, 3) float64, the neutral face's Bosphorus landmarks
    expressive : (e, n, 3) float64, each expression's vertices: every neutral vertex moved
        with its skin, so vertex i is the same skin point in every mesh
    names : tuple of e str
    """

    neutral: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray
    expressive: np.ndarray
    names: tuple


def _expression_meshes(identity, expressions, spacing_mm: float) -> ExpressionMeshes:
    identity = _as_identity(identity)
    scan = make_face(identity, spacing_mm=spacing_mm)
    mesh = FaceGrid.from_points(scan.points, scan.valid).mesh()
    neutral = np.ascontiguousarray(mesh.vertices)
    moved = [neutral + au_displacement(identity, weights, neutral[:, :2]) for weights in expressions.values()]
    expressive = np.stack(moved) if moved else np.empty((0,) + neutral.shape)
    return ExpressionMeshes(neutral, np.ascontiguousarray(mesh.faces), face_landmarks(identity), expressive,
                            tuple(expressions))


def elastic_faces(expressions=None, *, spacing_mm: float = 1.5) -> tuple[ExpressionMeshes, ExpressionMeshes]:
    """Source and target faces for the elastic expression model: the demo's two
    procedural people (:func:`demo_triplet`'s) as meshes, each with the same
    expressions on its own vertices (the target's are the truth a clone is measured
    against).

    Parameters
    ----------
    expressions : dict, optional
        Name -> AU weights (as :func:`make_face` takes them); default
        :data:`ELASTIC_EXPRESSIONS`.
    spacing_mm : float
        The meshes' vertex spacing: 1.5 mm gives about 6,000 vertices a face.
    """
    expressions = dict(ELASTIC_EXPRESSIONS if expressions is None else expressions)
    for name, weights in expressions.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"expressions: names must be non-empty strings, got {name!r}")
        _normalise_expression(weights)
    return (_expression_meshes(random_identity(DEMO_SOURCE_SEED), expressions, spacing_mm),
            _expression_meshes(random_identity(DEMO_TARGET_SEED), expressions, spacing_mm))


def afm_faces(shape=(150, 150)) -> list[FaceGrid]:
    """The embedded procedural faces resampled as face grids: the database the shipped
    average face (:func:`tpscore.face.average_face.build_average_face`) is built from."""
    return [resample_scan(scan.points, scan.landmarks, shape) for scan in embedded_faces()]


def face_point_cloud(n: int, seed: int = 0, jitter: float = 0.3, width: float = 150.0,
                     height: float = 180.0) -> np.ndarray:
    """n points (mm) on a face-like height field (a dome and a nose-like bump), on a
    jittered grid in x, y: quasi-uniform like the vertices of a resampled scan. The
    sparse kernels' tests and benchmarks fit on it."""
    rng = np.random.default_rng(seed)
    cols = int(round(np.sqrt(n * width / height)))
    rows = int(np.ceil(n / cols))
    x, y = np.meshgrid(np.linspace(-width / 2, width / 2, cols), np.linspace(-height / 2, height / 2, rows))
    spacing = width / (cols - 1)
    x = x.ravel()[:n] + rng.uniform(-jitter, jitter, n) * spacing
    y = y.ravel()[:n] + rng.uniform(-jitter, jitter, n) * spacing
    z = 60 * np.exp(-(x**2 / (2 * 55**2) + y**2 / (2 * 70**2))) + 18 * np.exp(
        -(x**2 / (2 * 9**2) + (y + 5) ** 2 / (2 * 16**2)))
    return np.stack([x, y, z], axis=1)
