#include "tpscore/rbf.hpp"

#include <Eigen/LU>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "tpscore/parallel.hpp"

// glibc declares the vector variants of log and exp (libmvec: _ZGVbN2v_log,
// _ZGVdN4v_log, _ZGVeN8v_log, ...) only under -ffast-math (bits/math-vector.h).
// Declaring them here lets the `#pragma omp simd` loops below call them without
// fast-math's other relaxations (NaN and infinity handling, reassociation).
// With them the tps loop at 22,500 x 60 went from 5.7 ms (scalar log) to 4.1 ms
// (SSE2 libmvec), 2.0 ms (AVX2 clone) and 1.3 ms (AVX-512 clone), one thread, on
// the development machine (an AMD EPYC with AVX-512).
#if defined(__GLIBC__) && defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
extern "C" {
double log(double) noexcept __attribute__((simd("notinbranch")));
double exp(double) noexcept __attribute__((simd("notinbranch")));
}
// One binary for every x86-64 CPU, the best loop picked at load time (ifunc):
// no -march=native. Measured above; x86-64-v3 brings AVX2 + FMA, v4 AVX-512.
#define TPSCORE_SIMD_CLONES \
    __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define TPSCORE_SIMD_CLONES
#endif

#if defined(__GNUC__)
#define TPSCORE_ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define TPSCORE_ALWAYS_INLINE inline
#endif

namespace tpscore {

namespace {

// Queries are evaluated in blocks of this many rows, laid out one array per axis, so
// the inner loop over a block is long, contiguous and has no remainder: every row
// goes through the same vector code whatever block or thread it falls in, which keeps
// the result independent of the thread count. 32..256 timed within 5% of each other
// (22,500 x 60, tps); 64 wastes the least on padding.
constexpr std::int64_t kBlock = 64;

// phi as a function of the squared distance d2 and e2 = epsilon^2 (same units).
template <RbfKernel Kernel>
TPSCORE_ALWAYS_INLINE double phi_of_d2(double d2, double e2) {
    if constexpr (Kernel == RbfKernel::tps) {
        // U(0) = 0 without a comparison: 0 * log(DBL_MIN) = 0, and adding DBL_MIN
        // changes no d2 above 1e-290 mm^2. A `d2 > 0 ? ... : 0` select is a
        // possibly-trapping comparison to GCC, which then keeps it as a branch and
        // does not vectorise the loop (unless built with -fno-trapping-math).
        return d2 * std::log(d2 + std::numeric_limits<double>::min());
    } else if constexpr (Kernel == RbfKernel::biharmonic) {
        return std::sqrt(d2);
    } else if constexpr (Kernel == RbfKernel::triharmonic) {
        return d2 * std::sqrt(d2);
    } else if constexpr (Kernel == RbfKernel::multiquadric) {
        return std::sqrt(1.0 + e2 * d2);
    } else {
        return std::exp(-e2 * d2);
    }
}

// acc (Kdim rows of kBlock) += sum_j w_j phi(|q - c_j|) for one block of queries.
// Kdim > 0 fuses phi and the accumulation (k = 1, 2, 3 are the common cases);
// Kdim == 0 handles any k through a block of phi values.
template <RbfKernel Kernel, int Kdim>
TPSCORE_ALWAYS_INLINE void accumulate_block_impl(double e2, const double* __restrict qx,
                                                 const double* __restrict qy,
                                                 const double* __restrict qz, const double* cx,
                                                 const double* cy, const double* cz,
                                                 std::int64_t n, const double* weights,
                                                 std::int64_t k, double* __restrict acc) {
    alignas(64) double u[kBlock];
    for (std::int64_t j = 0; j < n; ++j) {
        const double x = cx[j], y = cy[j], z = cz[j];
        if constexpr (Kdim > 0) {
            double w[Kdim];
            for (int c = 0; c < Kdim; ++c) w[c] = weights[c * n + j];
#pragma omp simd
            for (std::int64_t q = 0; q < kBlock; ++q) {
                const double dx = qx[q] - x, dy = qy[q] - y, dz = qz[q] - z;
                const double v = phi_of_d2<Kernel>(dx * dx + dy * dy + dz * dz, e2);
                for (int c = 0; c < Kdim; ++c) acc[c * kBlock + q] += w[c] * v;
            }
        } else {
#pragma omp simd
            for (std::int64_t q = 0; q < kBlock; ++q) {
                const double dx = qx[q] - x, dy = qy[q] - y, dz = qz[q] - z;
                u[q] = phi_of_d2<Kernel>(dx * dx + dy * dy + dz * dz, e2);
            }
            for (std::int64_t c = 0; c < k; ++c) {
                const double w = weights[c * n + j];
                double* __restrict a = acc + c * kBlock;
#pragma omp simd
                for (std::int64_t q = 0; q < kBlock; ++q) a[q] += w * u[q];
            }
        }
    }
}

template <RbfKernel Kernel>
TPSCORE_ALWAYS_INLINE void accumulate_block_k(double e2, const double* qx, const double* qy,
                                              const double* qz, const double* cx,
                                              const double* cy, const double* cz,
                                              std::int64_t n, const double* weights,
                                              std::int64_t k, double* acc) {
    switch (k) {
        case 1: accumulate_block_impl<Kernel, 1>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc); break;
        case 2: accumulate_block_impl<Kernel, 2>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc); break;
        case 3: accumulate_block_impl<Kernel, 3>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc); break;
        default: accumulate_block_impl<Kernel, 0>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
    }
}

TPSCORE_SIMD_CLONES
void accumulate_block(RbfKernel kernel, double e2, const double* qx, const double* qy,
                      const double* qz, const double* cx, const double* cy, const double* cz,
                      std::int64_t n, const double* weights, std::int64_t k, double* acc) {
    switch (kernel) {
        case RbfKernel::tps:
            accumulate_block_k<RbfKernel::tps>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::biharmonic:
            accumulate_block_k<RbfKernel::biharmonic>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::triharmonic:
            accumulate_block_k<RbfKernel::triharmonic>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::multiquadric:
            accumulate_block_k<RbfKernel::multiquadric>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
        case RbfKernel::gaussian:
            accumulate_block_k<RbfKernel::gaussian>(e2, qx, qy, qz, cx, cy, cz, n, weights, k, acc);
            break;
    }
}

template <RbfKernel Kernel>
TPSCORE_ALWAYS_INLINE void phi_row_impl(double e2, double x, double y, double z,
                                        const double* cx, const double* cy, const double* cz,
                                        std::int64_t n, double* __restrict out) {
#pragma omp simd
    for (std::int64_t j = 0; j < n; ++j) {
        const double dx = x - cx[j], dy = y - cy[j], dz = z - cz[j];
        out[j] = phi_of_d2<Kernel>(dx * dx + dy * dy + dz * dz, e2);
    }
}

// out[j] = phi(|(x, y, z) - c_j|) for j < n: one row of a kernel matrix.
TPSCORE_SIMD_CLONES
void phi_row(RbfKernel kernel, double e2, double x, double y, double z, const double* cx,
             const double* cy, const double* cz, std::int64_t n, double* out) {
    switch (kernel) {
        case RbfKernel::tps: phi_row_impl<RbfKernel::tps>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::biharmonic: phi_row_impl<RbfKernel::biharmonic>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::triharmonic: phi_row_impl<RbfKernel::triharmonic>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::multiquadric: phi_row_impl<RbfKernel::multiquadric>(e2, x, y, z, cx, cy, cz, n, out); break;
        case RbfKernel::gaussian: phi_row_impl<RbfKernel::gaussian>(e2, x, y, z, cx, cy, cz, n, out); break;
    }
}

bool uses_epsilon(RbfKernel kernel) {
    return kernel == RbfKernel::multiquadric || kernel == RbfKernel::gaussian;
}

// phi(s r) = g(s) phi'(r) (+ for tps a term s^2 ln s^2 r^2, which the side conditions
// P^T W = 0 turn into a constant, see rbf_fit): the factor between the kernel in
// original and in normalised coordinates.
double kernel_scale_factor(RbfKernel kernel, double scale) {
    switch (kernel) {
        case RbfKernel::tps: return scale * scale;
        case RbfKernel::biharmonic: return scale;
        case RbfKernel::triharmonic: return scale * scale * scale;
        default: return 1.0;  // gaussian, multiquadric: epsilon absorbs the scale
    }
}

std::string format_number(double value) {
    char buffer[64];
    std::snprintf(buffer, sizeof buffer, "%.3g", value);
    return buffer;
}

}  // namespace

int rbf_smoothing_sign(RbfKernel kernel) {
    return (kernel == RbfKernel::biharmonic || kernel == RbfKernel::multiquadric) ? -1 : 1;
}

RbfModel rbf_fit(const PointsRef& centres, const MatrixRef& values, RbfKernel kernel,
                 double epsilon, double smoothing) {
    const std::int64_t n = centres.rows();
    const std::int64_t k = values.cols();
    if (n < 1) throw std::invalid_argument("rbf_fit: no centres");
    if (values.rows() != n)
        throw std::invalid_argument("rbf_fit: values must have one row per centre");
    if (k < 1) throw std::invalid_argument("rbf_fit: values need at least one column");
    if (static_cast<int>(kernel) < 0 || static_cast<int>(kernel) > 4)
        throw std::invalid_argument("rbf_fit: unknown kernel");
    if (uses_epsilon(kernel) && !(epsilon > 0.0 && std::isfinite(epsilon)))
        throw std::invalid_argument("rbf_fit: epsilon must be finite and > 0");
    if (!(smoothing >= 0.0 && std::isfinite(smoothing)))
        throw std::invalid_argument("rbf_fit: smoothing must be finite and >= 0");

    RbfModel model;
    model.kernel = kernel;
    model.epsilon = uses_epsilon(kernel) ? epsilon : 0.0;
    model.smoothing = smoothing;
    model.centres = centres;

    // Normalise: centre on the bounding box, scale into the unit ball. The kernel
    // matrix and P = [1 x y z] then have entries of order 1, whatever the units
    // and the offset of the data (1e4 mm offsets, 1e-3 mm extents).
    const Eigen::RowVector3d lo = centres.colwise().minCoeff();
    const Eigen::RowVector3d hi = centres.colwise().maxCoeff();
    model.shift = 0.5 * (lo + hi);
    double scale = 0.0;
    for (std::int64_t i = 0; i < n; ++i)
        scale = std::max(scale, (centres.row(i) - model.shift).norm());
    if (!(scale > 0.0) || !std::isfinite(scale))
        throw std::domain_error("the centres do not span any volume (all coincide or are not finite)");
    model.scale = scale;
    model.epsilon_normalised = model.epsilon * scale;
    const double e2 = model.epsilon_normalised * model.epsilon_normalised;
    const double g = kernel_scale_factor(kernel, scale);
    // (K + sign lambda I) W + P A = Y in original units becomes, with K = g K' and
    // W = W' / g, (K' + sign (lambda / g) I) W' + P' A' = Y in normalised units.
    const double diagonal_shift = rbf_smoothing_sign(kernel) * smoothing / g;

    model.centre_x.resize(n);
    model.centre_y.resize(n);
    model.centre_z.resize(n);
    for (std::int64_t i = 0; i < n; ++i) {
        model.centre_x[i] = (centres(i, 0) - model.shift[0]) / scale;
        model.centre_y[i] = (centres(i, 1) - model.shift[1]) / scale;
        model.centre_z[i] = (centres(i, 2) - model.shift[2]) / scale;
    }
    const double* cx = model.centre_x.data();
    const double* cy = model.centre_y.data();
    const double* cz = model.centre_z.data();

    // The saddle-point matrix, column-major (what Eigen's blocked LU is tuned for).
    // It is symmetric, so column i is filled like a row.
    const std::int64_t size = n + 4;
    Eigen::MatrixXd system(size, size);
    parallel_for(static_cast<std::size_t>(n), 256, [&](std::size_t begin, std::size_t end) {
        for (std::size_t ii = begin; ii < end; ++ii) {
            const auto i = static_cast<std::int64_t>(ii);
            double* column = system.col(i).data();
            phi_row(kernel, e2, cx[i], cy[i], cz[i], cx, cy, cz, n, column);
            column[i] += diagonal_shift;
            column[n] = 1.0;
            column[n + 1] = cx[i];
            column[n + 2] = cy[i];
            column[n + 3] = cz[i];
        }
    });
    // Equilibrate: scale the polynomial columns and rows [1 x y z] to the size of the
    // kernel block. Large smoothing makes that block ~lambda' I, and without this the
    // matrix is badly scaled (rcond ~ 1 / lambda'^2) while the problem itself is not:
    // the rcond test below would then refuse a perfectly good fit. With the scaling,
    // the unknowns are [W; A / polynomial_scale].
    double polynomial_scale = system.topLeftCorner(n, n).cwiseAbs().maxCoeff();
    if (!(polynomial_scale > 0.0) || !std::isfinite(polynomial_scale)) polynomial_scale = 1.0;
    system.bottomLeftCorner(4, n) *= polynomial_scale;
    system.topRightCorner(n, 4) = system.bottomLeftCorner(4, n).transpose();
    system.bottomRightCorner(4, 4).setZero();

    Eigen::MatrixXd rhs = Eigen::MatrixXd::Zero(size, k);
    rhs.topRows(n) = values;

    // Partial pivoting rather than FullPivLU: the matrix is nonsingular whenever the
    // centres are distinct and not coplanar (checked by the caller), so full
    // pivoting's rank revelation buys nothing, while PartialPivLU is blocked (matrix
    // products inside): measured 0.043 s against 0.23 s at n = 1000 and 0.28 s
    // against 4.0 s at n = 2000 (one thread). The rcond estimate below still
    // catches a near-singular system.
    const Eigen::PartialPivLU<Eigen::MatrixXd> lu(system);
    model.rcond = lu.rcond();
    if (!(model.rcond > std::numeric_limits<double>::epsilon())) {
        throw std::domain_error(
            "the RBF system is numerically singular (reciprocal condition estimate " +
            format_number(model.rcond) +
            "): centres nearly coincide or nearly lie on a plane" +
            (uses_epsilon(kernel) ? std::string(", or epsilon is too small for the centres' spacing")
                                  : std::string()) +
            "; smoothing > 0 regularises it");
    }
    Eigen::MatrixXd solution = lu.solve(rhs);
    // One step of iterative refinement (O(n^2 k), against O(n^3) for the LU): it
    // recovers the digits lost to the residual of the factorisation, which matters
    // when values carry a large offset (coordinates 1e4 mm from the origin).
    solution += lu.solve(rhs - system * solution);
    if (!solution.allFinite())
        throw std::domain_error("the RBF system could not be solved: the solution is not finite");

    model.weights_normalised = solution.topRows(n);
    model.affine_normalised = polynomial_scale * solution.bottomRows(4);
    const Eigen::MatrixXd& w = model.weights_normalised;

    // trace(W^T K W) = trace(W'^T K' W') / g (the tps term drops out: P^T W' = 0).
    const double energy_normalised =
        (system.topLeftCorner(n, n) * w).cwiseProduct(w).sum() - diagonal_shift * w.squaredNorm();
    model.bending_energy = energy_normalised / g;

    // Back to original coordinates. f(x) = A'_0 + x' A'_xyz + sum W'_i phi'(r'_i) with
    // x' = (x - shift) / s and phi'(r') = (phi(r) - c(r)) / g, where c(r) = ln(s^2) r^2
    // for tps and 0 otherwise. Since P^T W' = 0, sum_i W'_i r_i^2 = s^2 sum_i W'_i |p'_i|^2
    // does not depend on x: it moves into the constant row of A.
    model.weights = MatrixX(w / g);
    model.affine = MatrixX(4, k);
    const Eigen::MatrixXd linear = model.affine_normalised.bottomRows(3) / scale;
    model.affine.bottomRows(3) = linear;
    Eigen::RowVectorXd constant = model.affine_normalised.row(0) - model.shift * linear;
    if (kernel == RbfKernel::tps) {
        const Eigen::VectorXd squared_norms =
            (model.centre_x.array().square() + model.centre_y.array().square() +
             model.centre_z.array().square())
                .matrix();
        constant -= std::log(scale * scale) * (squared_norms.transpose() * w);
    }
    model.affine.row(0) = constant;

    if (k == 3) {
        // f(x) - x with x = shift + s x': subtract the identity in normalised form.
        model.displacement_affine_normalised = model.affine_normalised;
        model.displacement_affine_normalised.row(0) -= model.shift;
        for (int axis = 0; axis < 3; ++axis)
            model.displacement_affine_normalised(1 + axis, axis) -= scale;
    }
    return model;
}

MatrixX rbf_evaluate(const RbfModel& model, const PointsRef& queries, bool displacement) {
    MatrixX out(queries.rows(), model.value_dim());
    rbf_evaluate(model, queries, displacement, out);
    return out;
}

void rbf_evaluate(const RbfModel& model, const PointsRef& queries, bool displacement,
                  Eigen::Ref<MatrixX> out) {
    const std::int64_t m = queries.rows();
    const std::int64_t n = model.size();
    const std::int64_t k = model.value_dim();
    if (displacement && k != 3)
        throw std::invalid_argument("rbf_evaluate: the displacement needs 3 values per centre");
    if (out.rows() != m || out.cols() != k)
        throw std::invalid_argument("rbf_evaluate: out must have shape (m, k)");
    if (m == 0) return;

    const Eigen::MatrixXd& affine =
        displacement ? model.displacement_affine_normalised : model.affine_normalised;
    const double e2 = model.epsilon_normalised * model.epsilon_normalised;
    const double scale = model.scale;
    const Eigen::RowVector3d shift = model.shift;
    const std::int64_t blocks = (m + kBlock - 1) / kBlock;
    // About 200k kernel evaluations (~0.2 ms) per thread at least: below that,
    // starting a thread costs more than it saves.
    const std::int64_t min_blocks = std::max<std::int64_t>(1, 200000 / (kBlock * n));
    const std::int64_t workers =
        std::clamp<std::int64_t>(blocks / min_blocks, 1, std::max(1, num_threads()));
    // Workers take a few blocks at a time from a shared counter instead of one fixed
    // share each: when another process holds a core, the threads that do run take
    // over the rest rather than waiting for a descheduled one. Which thread computes
    // a row does not change how it is computed, so results stay thread-independent.
    constexpr std::int64_t kGrain = 4;
    std::atomic<std::int64_t> next_block{0};

    auto evaluate_blocks = [&](std::size_t, std::size_t) {
        alignas(64) double qx[kBlock], qy[kBlock], qz[kBlock];
        std::vector<double> acc(static_cast<std::size_t>(k * kBlock));
        for (;;) {
            const std::int64_t begin = next_block.fetch_add(kGrain, std::memory_order_relaxed);
            if (begin >= blocks) break;
            const std::int64_t end = std::min(blocks, begin + kGrain);
            for (std::int64_t b = begin; b < end; ++b) {
                const std::int64_t first = b * kBlock;
                const std::int64_t count = std::min(kBlock, m - first);
                for (std::int64_t q = 0; q < kBlock; ++q) {
                    // The last block is padded with copies of its last row.
                    const std::int64_t row = first + std::min(q, count - 1);
                    qx[q] = (queries(row, 0) - shift[0]) / scale;
                    qy[q] = (queries(row, 1) - shift[1]) / scale;
                    qz[q] = (queries(row, 2) - shift[2]) / scale;
                }
                for (std::int64_t c = 0; c < k; ++c) {
                    double* a = acc.data() + c * kBlock;
                    const double a0 = affine(0, c), ax = affine(1, c), ay = affine(2, c),
                                 az = affine(3, c);
                    for (std::int64_t q = 0; q < kBlock; ++q)
                        a[q] = a0 + ax * qx[q] + ay * qy[q] + az * qz[q];
                }
                accumulate_block(model.kernel, e2, qx, qy, qz, model.centre_x.data(),
                                 model.centre_y.data(), model.centre_z.data(), n,
                                 model.weights_normalised.data(), k, acc.data());
                for (std::int64_t q = 0; q < count; ++q)
                    for (std::int64_t c = 0; c < k; ++c) out(first + q, c) = acc[c * kBlock + q];
            }
        }
    };
    // One chunk per worker: parallel_for provides the threads, the counter the work.
    parallel_for(static_cast<std::size_t>(workers), 1, evaluate_blocks);
}

MatrixX rbf_evaluation_matrix(const RbfModel& model, const PointsRef& queries) {
    const std::int64_t m = queries.rows();
    const std::int64_t n = model.size();
    MatrixX out(m, n + 4);
    if (m == 0) return out;
    const Eigen::VectorXd cx = model.centres.col(0), cy = model.centres.col(1), cz = model.centres.col(2);
    const double e2 = model.epsilon * model.epsilon;
    const std::size_t min_rows = static_cast<std::size_t>(std::max<std::int64_t>(1, 100000 / (n + 4)));
    parallel_for(static_cast<std::size_t>(m), min_rows, [&](std::size_t begin, std::size_t end) {
        for (std::size_t ii = begin; ii < end; ++ii) {
            const auto i = static_cast<std::int64_t>(ii);
            double* row = out.row(i).data();
            const double x = queries(i, 0), y = queries(i, 1), z = queries(i, 2);
            phi_row(model.kernel, e2, x, y, z, cx.data(), cy.data(), cz.data(), n, row);
            row[n] = 1.0;
            row[n + 1] = x;
            row[n + 2] = y;
            row[n + 3] = z;
        }
    });
    return out;
}

}  // namespace tpscore
