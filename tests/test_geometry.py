"""The shared geometric and statistical helpers."""
from __future__ import annotations

import numpy as np

from tpscore.geometry import mesh_edges, robust_scale, tukey_weights, vertex_adjacency


def test_edges_of_two_triangles_sharing_one():
    edges = mesh_edges([[0, 1, 2], [2, 1, 3]])
    np.testing.assert_array_equal(edges, [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])
    adjacency = vertex_adjacency(4, [[0, 1, 2], [2, 1, 3]]).toarray()
    np.testing.assert_array_equal(adjacency, adjacency.T)
    assert adjacency.sum() == 2 * 5 and adjacency[0, 3] == 0


def test_robust_scale_ignores_outliers_and_keeps_its_floor():
    rng = np.random.default_rng(0)
    residuals = rng.normal(0.0, 2.0, 20000)
    residuals[:500] = 1e6
    # the median of |r| of a normal distribution is 0.6745 sigma
    assert abs(robust_scale(residuals) - 2.0) < 0.1
    assert robust_scale(residuals + 5.0, centred=True) < 2.1
    assert robust_scale(np.zeros(10), floor=0.3) == 0.3
    assert robust_scale([], floor=0.7) == 0.7


def test_tukey_weights():
    w = tukey_weights([0.0, 0.5, 1.0, -0.5, 2.0], 1.0)
    np.testing.assert_allclose(w, [1.0, 0.5625, 0.0, 0.5625, 0.0])


def test_check_options_names_the_class_field_and_value():
    from dataclasses import dataclass

    import pytest

    from tpscore._validation import check_options

    @dataclass
    class Knobs:
        width: float = 1.0
        gap: float = 0.0
        steps: int = 3
        repeats: int = 0
        fast: bool = True
        mode: str = "a"

    def check(knobs):
        check_options(knobs, positive=("width",), non_negative=("gap",), counts=("steps", ("repeats", 0)),
                      flags=("fast",), choices={"mode": ("a", "b")})

    check(Knobs())
    for change, words in [(dict(width=0.0), "Knobs.width.*> 0"), (dict(gap=np.nan), "Knobs.gap"),
                          (dict(steps=2.5), "Knobs.steps.*whole"), (dict(repeats=-1), "Knobs.repeats.*>= 0"),
                          (dict(fast="yes"), "Knobs.fast"), (dict(mode="c"), "Knobs.mode.*one of"),
                          (dict(width="wide"), "Knobs.width must be a number")]:
        with pytest.raises(ValueError, match=words):
            check(Knobs(**change))
