"""Expression transfer (docs/design.md, method 1): an AU modelled on a source person and
animated on a target person. :func:`transfer` (also ``tpscore.transfer``) runs the whole
pipeline; the stages are modules of their own (alignment, texture, registration with its
landmark pairs, the cut at the openings, modelling, animation, and the parts of the method
as published); :mod:`~tpscore.expression.methods` holds the two methods a transfer picks from."""
from __future__ import annotations

from .action_units import ActionUnit, ActionUnitLibrary, Activation, ControlPoint, WholeExpression, default_library
from .alignment import RigidAlignment, align_rigid, fit_mirror_symmetry
from .animation import Animation
from .cut_motion import CutMotion
from .methods import DenseTransfer, PublishedTransfer, animate, model_expression, transfer_method
from .mirror import MirroredMotion
from .modelling import ExpressionModel, PersonMismatchError, PersonMismatchWarning
from .options import TransferOptions
from .pipeline import TransferResult, transfer
from .registration import DenseMotion, MotionOptions, register_surfaces
from .texture import TextureMatches, TextureOptions, TextureWarning, track_texture

__all__ = ["transfer", "TransferOptions", "TransferResult", "Animation", "animate", "ExpressionModel",
           "model_expression", "ActionUnit", "ActionUnitLibrary", "Activation", "ControlPoint",
           "default_library", "RigidAlignment", "align_rigid", "fit_mirror_symmetry", "MirroredMotion",
           "DenseMotion", "MotionOptions", "register_surfaces", "TextureMatches", "TextureOptions",
           "TextureWarning", "track_texture", "PersonMismatchWarning", "PersonMismatchError", "WholeExpression", "CutMotion",
           "DenseTransfer", "PublishedTransfer", "transfer_method"]
