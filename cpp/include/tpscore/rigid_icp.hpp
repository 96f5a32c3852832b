// Rigid point-to-plane ICP of sample points onto a triangle mesh.
#pragma once

#include <cstdint>

#include <Eigen/Dense>

#include "tpscore/closest_point.hpp"
#include "tpscore/types.hpp"

namespace tpscore {

struct RigidIcpSettings {
    int iterations = 30;          ///< most iterations
    double tukey_factor = 4.0;    ///< pairs beyond this many robust scales get weight 0
    double min_scale = 0.3;       ///< lower bound of the robust scale (mm)
    double tolerance = 1e-3;      ///< stop when the update moves no sample by more (mm)
};

struct RigidIcpResult {
    Eigen::Matrix4d matrix;       ///< the rigid map, start included
    int iterations = 0;           ///< iterations run (the last one may have stopped early)
    double inlier_rms = 0.0;      ///< weighted rms point-to-plane distance (NaN before any step)
};

/// The rigid map taking `sample` (m, 3) onto the surface `fixed`, refined from `start`
/// by linearised point-to-plane steps. Each iteration moves the sample, finds its
/// closest points, weighs each pair by a Tukey weight of its distance (scale:
/// 1.4826 x the median distance of the pairs whose prior exceeds 0.5, or of all pairs
/// when none does, at least settings.min_scale) times its prior, and solves the 6 x 6
/// normal equations for a rotation vector and a translation about the weighted
/// centroid. Stops after settings.iterations, when the weights sum to less than 6, or
/// when the step moves no sample point by more than settings.tolerance.
/// face_normals holds the unit normal of every triangle of `fixed` (t x 3, original
/// order); prior has m entries. The closest points run on `workers` threads (0: all).
RigidIcpResult rigid_icp(const MeshSurface& fixed, const double* face_normals, const PointsRef& sample,
                         const double* prior, const Eigen::Matrix4d& start, const RigidIcpSettings& settings,
                         int workers = 0);

}  // namespace tpscore
