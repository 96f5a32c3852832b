"""The choices of an expression transfer, in one frozen, validated options object."""
from __future__ import annotations

from dataclasses import dataclass

from .._validation import check_options
from .correspondence import CORRESPONDENCES
from .registration import MotionOptions
from .texture import TextureOptions

__all__ = ["TransferOptions", "METHODS"]

#: ``"default"``: the source's motion registered densely (with its texture when the
#: scans have colour images) and carried onto the target; ``"published"``: the method as
#: published (see :meth:`TransferOptions.published`).
METHODS = ("default", "published")


@dataclass(frozen=True)
class TransferOptions:
    """Choices of the transfer pipeline. The defaults are the best measured ones
    (``benchmarks/FIDELITY.md``).

    Attributes
    ----------
    method : {"default", "published"}
        ``"default"``: the source's expressive scan is aligned rigidly onto its neutral
        scan, its motion registered densely (:func:`tpscore.register_surfaces`, with the
        scans' texture when both have colour images) and carried onto the target
        through the landmark correspondence. ``"published"``: the method as published
        (see :meth:`published`).
    mirror_average : bool
        For expressions that move both sides of the face (every AU without ``L`` or
        ``R``, and emotions), average the registered field with its mirror image across
        the source's plane of symmetry, and the carried field across the target's
        (:class:`tpscore.expression.mirror.MirroredMotion`). One-sided AUs are left as they
        are.
    transition_mm : float
        Width of the smooth blend across the upper/lower face boundary (0 = hard seam).
    side_transition_mm : float
        Width of the smooth blend across the midline for one-sided AUs (``12L``).
    upper_spill : float
        Upper-face motion is kept below the boundary where it continues the motion
        above it (the brow muscles also move the nasal root and bridge): where it is at
        least this fraction of the upper face's peak, no larger than the peak, and
        connected to it (0 = the boundary cuts it).
    merge_landmarks_mm : float
        Landmarks of one face closer than this are merged before a landmark TPS: the
        inner-lip landmarks of a closed mouth nearly coincide and would fold the map.
    correspondence : {"landmarks", "adapted"}
        Where each target point reads the source's motion. ``"landmarks"``: a TPS
        through the 22 landmark pairs. ``"adapted"``: the target's neutral grid fitted
        onto the source's neutral scan by the template adaptation
        (:func:`tpscore.adapt`), which follows the two faces' shapes between the
        landmarks: better by about 0.01-0.03 in residual ratio on most codes
        (``benchmarks/FIDELITY.md``), for about a second per pair of faces, paid once
        per pair of grids a session transfers between (a rig's or a batch's other
        expressions reuse it).
    motion : MotionOptions
        Settings of the dense registration.
    texture : TextureOptions
        Settings of the texture tracking.
    check_landmarks : bool
        Refuse a face whose landmarks fit no face (:class:`ImplausibleLandmarksError`:
        shuffled or mislabelled); False only warns.
    allow_other_person : bool
        Carry on when the source's expressive scan fits its neutral scan so badly that
        it is another person's (:class:`PersonMismatchError`); it is then only warned.
    """

    method: str = "default"
    mirror_average: bool = True
    transition_mm: float = 10.0
    side_transition_mm: float = 10.0
    upper_spill: float = 0.1
    merge_landmarks_mm: float = 3.0
    correspondence: str = "landmarks"
    motion: MotionOptions = MotionOptions()
    texture: TextureOptions = TextureOptions()
    check_landmarks: bool = True
    allow_other_person: bool = False

    def __post_init__(self):
        check_options(self, non_negative=("transition_mm", "side_transition_mm", "upper_spill",
                                          "merge_landmarks_mm"),
                      flags=("mirror_average", "check_landmarks", "allow_other_person"), choices={"method": METHODS, "correspondence": CORRESPONDENCES})
        if self.method == "published" and self.correspondence != "landmarks":
            raise ValueError(f"TransferOptions.correspondence={self.correspondence!r} needs method='default': the "
                             "method as published moves its control points through the landmark TPS")
        if not isinstance(self.motion, MotionOptions):
            raise ValueError(f"TransferOptions.motion must be a MotionOptions, got {type(self.motion).__name__}")
        if not isinstance(self.texture, TextureOptions):
            raise ValueError(f"TransferOptions.texture must be a TextureOptions, got {type(self.texture).__name__}")

    @classmethod
    def published(cls) -> "TransferOptions":
        """The method as published (docs/design.md, method 1): each scan normalised on its own
        landmarks by the affine map T = A B^-1; the AU's control points mapped onto the
        expressive scan by the landmark TPS and snapped to its nearest vertex; moved onto
        the target by the landmark TPS (nearest-vertex snap), their motion scaled by the
        ratio of the mouth widths in the lower face; each region warped by a TPS
        through the control points alone, with a hard seam between the regions."""
        return cls(method="published", mirror_average=False, transition_mm=0.0, merge_landmarks_mm=0.0)
