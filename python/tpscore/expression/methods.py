"""The two ways of transferring an expression, each one object that a transfer picks
once (:func:`transfer_method`) and whose steps it runs in order: how the faces are
normalised, how the expressive scan is brought onto the neutral one, how the source's
motion is modelled and how it is carried onto the target.

- :class:`DenseTransfer` (the default): the expressive scan aligned rigidly, the
  source's motion registered densely (with its texture, cut at the openings it
  opened or closed), averaged with its mirror image for a bilateral expression, read
  on the target through the landmark correspondence and weighted by the AU's region.
- :class:`PublishedTransfer`: the method as published (docs/transfer.md): every face
  normalised by the affine map of four landmarks, each AU's control points moved by
  the landmark TPS and snapped to the nearest vertex, each region of the target
  warped by a TPS through them; an emotion is its recipe of AUs.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..face.grid import FaceGrid
from ..face.landmarks import landmark_map
from ..face.normalise import NormalisedFace, normalise_face
from .action_units import ActionUnitLibrary, Activation, shipped_library
from .animation import Animation, by_region, carry, field_labels
from .modelling import (ControlPointMotion, ExpressionModel, activation_weight, align_expressive, dense_motion,
                        mirrored, needs_realignment, openings, place_control_points, realigned, registration_grid,
                        still_weight)
from .options import TransferOptions
from .published import model_control_points, warp_regions

__all__ = ["DenseTransfer", "PublishedTransfer", "transfer_method", "model_expression", "animate"]


class DenseTransfer:
    """The default transfer (see the module's text)."""

    normalisation = "similarity"

    def __init__(self, options: TransferOptions, reference: NormalisedFace, library: ActionUnitLibrary):
        self.options, self.reference, self.library = options, reference, library

    def labels(self, activations: Sequence[Activation]) -> list[str]:
        return field_labels(activations)

    def uses_mirror(self, activations: Sequence[Activation]) -> bool:
        """Whether the motion is averaged with its mirror image: for an expression that
        moves both sides alike."""
        return self.options.mirror_average and all(act.bilateral for act in activations)

    def prepare(self, neutral: NormalisedFace) -> None:
        """What the source's registration needs of its neutral face alone (made ahead):
        its registration grid and its openings."""
        registration_grid(neutral, self.options.motion)
        openings(neutral)

    def align(self, neutral: NormalisedFace, neutral_grid: FaceGrid, expressive_grid: FaceGrid,
              activations: Sequence[Activation]) -> NormalisedFace:
        still = still_weight(expressive_grid, activations, self.library, self.reference.landmarks)
        return align_expressive(neutral, neutral_grid, expressive_grid, still,
                                allow_other_person=self.options.allow_other_person)

    def model(self, neutral: NormalisedFace, expressive: NormalisedFace,
              activations: Sequence[Activation]) -> ExpressionModel:
        dense = dense_motion(neutral, expressive, self.options.motion, self.options.texture)
        if needs_realignment(activations, self.library, self.reference.landmarks):
            # the alignment knew no part to be still, only the parts that move least
            dense = realigned(dense, neutral)
        if self.uses_mirror(activations):
            dense = mirrored(dense, neutral)
        to_source = landmark_map(self.reference.landmarks, neutral.landmarks,
                                 merge_mm=self.options.merge_landmarks_mm, what="reference -> source")
        motions = []
        for act in activations:
            if act.whole:
                empty = np.zeros((0, 3))
                motions.append(ControlPointMotion(act, (), empty, empty))
                continue
            points = neutral.snap(to_source(place_control_points(act.action_unit, self.reference)), "surface")
            weights = act.action_unit.side_weights(act.side) * act.weight
            motions.append(ControlPointMotion(act, tuple(act.action_unit.names), points,
                                              dense(points) * weights[:, None]))
        return ExpressionModel(neutral, motions, self.reference, self.library, dense)

    def animate(self, model: ExpressionModel, target: NormalisedFace) -> Animation:
        o = self.options
        return carry(model, target, transition_mm=o.transition_mm, side_transition_mm=o.side_transition_mm,
                     upper_spill=o.upper_spill, merge_landmarks_mm=o.merge_landmarks_mm,
                     correspondence=o.correspondence)


class PublishedTransfer:
    """The method as published (see the module's text)."""

    normalisation = "affine"

    def __init__(self, options: TransferOptions, reference: NormalisedFace, library: ActionUnitLibrary):
        self.options, self.reference, self.library = options, reference, library

    def _action_units(self, activations: Sequence[Activation]) -> list[Activation]:
        return [au for act in activations for au in self.library.recipe(act)]

    def labels(self, activations: Sequence[Activation]) -> list[str]:
        return field_labels(self._action_units(activations))

    def uses_mirror(self, activations: Sequence[Activation]) -> bool:
        return False

    def prepare(self, neutral: NormalisedFace) -> None:
        """Nothing: the method has no registration."""

    def align(self, neutral: NormalisedFace, neutral_grid: FaceGrid, expressive_grid: FaceGrid,
              activations: Sequence[Activation]) -> NormalisedFace:
        # every scan is normalised on its own landmarks
        return normalise_face(expressive_grid, self.reference.landmarks, self.normalisation)

    def model(self, neutral: NormalisedFace, expressive: NormalisedFace,
              activations: Sequence[Activation]) -> ExpressionModel:
        moved = model_control_points(neutral, expressive, self._action_units(activations), self.reference,
                                     lambda au: place_control_points(au, self.reference),
                                     self.options.merge_landmarks_mm)
        motions = [ControlPointMotion(*m) for m in moved]
        return ExpressionModel(neutral, motions, self.reference, self.library, None)

    def animate(self, model: ExpressionModel, target: NormalisedFace) -> Animation:
        grid = target.grid

        def region_weight(region: str) -> np.ndarray:
            first = next(m.activation for m in model.motions if m.activation.action_unit.region == region)
            return activation_weight(first, grid.points, target.landmarks, self.library, self.reference.landmarks,
                                     self.options.transition_mm)

        labels, fields, controls, moved = warp_regions(by_region(model.motions), model.source.landmarks, target,
                                                       region_weight, self.options.merge_landmarks_mm)
        return Animation(target, labels, fields, controls, moved)


_METHODS = {"default": DenseTransfer, "published": PublishedTransfer}


def transfer_method(options: TransferOptions, reference: NormalisedFace, library: ActionUnitLibrary):
    """The method object the options name (``options.method``)."""
    return _METHODS[options.method](options, reference, library)


def model_expression(source_neutral: NormalisedFace, source_expressive: NormalisedFace,
                     activations: Sequence[Activation], reference: NormalisedFace,
                     options: TransferOptions = TransferOptions(),
                     library: ActionUnitLibrary | None = None) -> ExpressionModel:
    """The source's motion (both faces in the reference frame, the expressive one aligned
    by the method's :meth:`align`), by the method the options name."""
    method = transfer_method(options, reference, library or shipped_library())
    return method.model(source_neutral, source_expressive, activations)


def animate(model: ExpressionModel, target: NormalisedFace, options: TransferOptions = TransferOptions()) -> Animation:
    """Carry a modelled expression onto a normalised target, by the method the options name."""
    return transfer_method(options, model.reference, model.library).animate(model, target)
