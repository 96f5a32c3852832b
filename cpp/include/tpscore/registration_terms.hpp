// The data terms of the dense registration (tpscore.expression.registration): for each
// data point, its symmetric 3 x 3 weight block and right-hand side in the normal
// equations of the B-spline field, from its pair on the expressive surface.
//
// Each function follows the NumPy reference (tpscore.reference.registration) operation
// by operation, in its order and with each product rounded on its own (the file is
// built without fused multiply-adds), so the two agree to the bit and a transfer's
// result does not depend on which ran:
// - a 3-vector dot product u . v is ((0 + u0 v0) + u2 v2) + u1 v1, the order NumPy's
//   einsum("ij,ij->i") takes on x86-64 (two-lane SIMD, the third term into lane 0),
//   which the registration used before these kernels;
// - a length is sqrt((x0^2 + x1^2) + x2^2), as numpy.linalg.norm along a row;
// - a median is the middle value, or the mean (a + b) / 2 of the two middle ones.
// Blocks hold the entries (0,0) (0,1) (0,2) (1,1) (1,2) (2,2); all arrays are row-major.
#pragma once

#include <cstdint>

namespace tpscore {

/// The point-to-plane term of m pairs: each pulls its data point along the surface
/// normal n toward its closest point p with weight w = Tukey(distance; tukey_factor *
/// scale) * prior, where scale = max(1.4826 median(distances of the pairs on the
/// surface), floor), and w = 0 for a pair off the surface (|along| < 0.8 distance -
/// 0.05: a closest point on the scan's outline or a hole's rim). Writes blocks (m, 6)
/// = w n n^T, rhs (m, 3) = w ((p - sample) . n) n, along (m,) = (moved - p) . n and
/// weight (m,) = w. Preconditions: all inputs finite.
void point_to_plane_terms(std::int64_t m, const double* sample, const double* moved, const double* closest,
                          const double* distances, const double* normals, const double* prior, double floor,
                          double tukey_factor, double* blocks, double* rhs, double* along, double* weight);

/// The texture term of m data points: each pulls along the surface (P = I - n n^T)
/// toward its texture match q with weight w = Tukey(|P (moved - q)|; tukey_factor *
/// scale) * prior for prior > 0 (0 otherwise), where scale = max(1.4826 median(those
/// residuals of the points with prior > 0), floor). Writes blocks (m, 6) = w P and rhs
/// (m, 3) = w P (q - sample). Preconditions: all inputs finite.
void texture_pull_terms(std::int64_t m, const double* sample, const double* moved, const double* targets,
                        const double* normals, const double* prior, double floor, double tukey_factor,
                        double* blocks, double* rhs);

}  // namespace tpscore
