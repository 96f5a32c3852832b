"""Template adaptation (docs/design.md, method 2): deform a template mesh onto a scan.

Given a template (any topology) with feature points and a scan (a mesh or a Bosphorus
grid, noisy, with holes) with the corresponding feature points, :func:`adapt` returns
the template's vertices moved onto the scan -- same topology, the scan's shape -- and the
error figures of each level. The stages, one module each:

* :mod:`~tpscore.adaptation.setup`: inputs, feature points, wrong ones found by leave-one-out
  prediction, the calibration (:mod:`~tpscore.adaptation.calibration`);
* :mod:`~tpscore.adaptation.levels`: level 0's global RBF, then the refinement levels of
  :mod:`~tpscore.adaptation.surface` (default) or :mod:`~tpscore.adaptation.interpolate` (the
  published scheme, with the pairs of :mod:`~tpscore.adaptation.correspondence`), scored by
  :mod:`~tpscore.adaptation.fit_error`;
* :mod:`~tpscore.adaptation.snap`, :mod:`~tpscore.adaptation.fill` and :mod:`~tpscore.adaptation.rigid`:
  what the surface levels leave to do vertex by vertex;
* :mod:`~tpscore.adaptation.pipeline`: :func:`adapt`, the stages in order.

The options are one :class:`AdaptOptions`; docs/adaptation.md explains them.
"""
from __future__ import annotations

from .calibration import AxesCalibration, axes_calibration, calibrate
from .correspondence import FeatureMesh, curvature_features
from .options import DEFAULT_FEATURE_BOX, AdaptOptions
from .pipeline import adapt
from .result import AdaptationWarning, AdaptLevel, AdaptResult, Correspondences

__all__ = [
    "AdaptOptions",
    "AdaptResult",
    "AdaptLevel",
    "AdaptationWarning",
    "AxesCalibration",
    "Correspondences",
    "DEFAULT_FEATURE_BOX",
    "FeatureMesh",
    "adapt",
    "axes_calibration",
    "calibrate",
    "curvature_features",
]
