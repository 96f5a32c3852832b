// Dense supernode kernels (see tpscore/supernode_kernels.hpp).
//
// This file is compiled twice. The plain build holds the baseline kernels and the
// dispatcher; on x86-64 a second build with -march=x86-64-v3 and
// TPSCORE_DENSE_X86_64_V3 defined holds the AVX2 + FMA kernels only.
#if defined(TPSCORE_DENSE_X86_64_V3)
// Both builds instantiate the same Eigen templates. Under the same names the linker
// would keep one copy of each for both builds, and the baseline kernels could end up
// executing AVX2 code on a CPU without it. Renaming Eigen's namespace in this build
// keeps the two sets of instantiations apart. (#include <...> lines are not macro-
// expanded, so the headers are still found.) For the same reason this file uses no
// standard-library templates that could be instantiated out of line.
#define Eigen tpscore_eigen_x86_64_v3
#define TPSCORE_DENSE_NAMESPACE supernode_x86_64_v3
#define TPSCORE_DENSE_ISA_NAME "x86-64-v3"
#else
#define TPSCORE_DENSE_NAMESPACE supernode_baseline
#define TPSCORE_DENSE_ISA_NAME "baseline"
#endif

#include "tpscore/supernode_kernels.hpp"

#include <Eigen/Core>
#include <cmath>
#if !defined(TPSCORE_DENSE_X86_64_V3)
#include "tpscore/simd.hpp"
#endif

namespace tpscore {
namespace TPSCORE_DENSE_NAMESPACE {

namespace {

using Matrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic>;
using MatrixMap = Eigen::Map<Matrix>;
using ConstMatrixMap = Eigen::Map<const Matrix>;
using VectorMap = Eigen::Map<Eigen::VectorXd>;
using ConstVectorMap = Eigen::Map<const Eigen::VectorXd>;

// Columns per step of the blocked diagonal-block factorisation: the unblocked kernel
// below runs on a kBlock-wide square (a few dozen KB, in L1/L2), and everything else
// is a triangular solve or a rank-kBlock update that runs in Eigen's blocked
// matrix-product kernels.
constexpr std::ptrdiff_t kBlock = 48;

// Right-looking Cholesky of the (n, n) lower triangle at `a` (leading dimension lda),
// column by column; its inner loops are unit-stride multiply-adds. Returns -1 or the
// first non-positive pivot's index.
std::ptrdiff_t factor_unblocked(double* a, std::ptrdiff_t lda, std::ptrdiff_t n, double* pivots) {
    for (std::ptrdiff_t j = 0; j < n; ++j) {
        double* column = a + j * lda;
        const double pivot = column[j];
        pivots[j] = pivot;
        if (!(pivot > 0.0)) return j;
        const double diagonal = std::sqrt(pivot);
        column[j] = diagonal;
        for (std::ptrdiff_t i = j + 1; i < n; ++i) column[i] /= diagonal;
        for (std::ptrdiff_t c = j + 1; c < n; ++c) {
            const double factor = column[c];
            double* target = a + c * lda;
            for (std::ptrdiff_t i = c; i < n; ++i) target[i] -= factor * column[i];
        }
    }
    return -1;
}

std::ptrdiff_t factor_front(double* panel, std::ptrdiff_t rows, std::ptrdiff_t columns,
                            double* update, double* pivots) {
    MatrixMap front(panel, rows, columns);
    // The diagonal block, blocked: factorise kBlock columns, solve for the rows of the
    // block below them, update the rest of the diagonal block.
    for (std::ptrdiff_t k = 0; k < columns; k += kBlock) {
        const std::ptrdiff_t width = columns - k < kBlock ? columns - k : kBlock;
        const std::ptrdiff_t failed = factor_unblocked(panel + k * rows + k, rows, width, pivots + k);
        if (failed >= 0) return k + failed;
        const std::ptrdiff_t rest = columns - k - width;
        if (rest == 0) break;
        auto diagonal = front.block(k, k, width, width);
        auto below = front.block(k + width, k, rest, width);
        diagonal.transpose().triangularView<Eigen::Upper>().solveInPlace<Eigen::OnTheRight>(below);
        front.block(k + width, k + width, rest, rest)
            .selfadjointView<Eigen::Lower>()
            .rankUpdate(below, -1.0);
    }
    const std::ptrdiff_t remaining = rows - columns;
    if (remaining > 0) {
        auto l11 = front.topRows(columns);
        auto l21 = front.bottomRows(remaining);
        l11.transpose().triangularView<Eigen::Upper>().solveInPlace<Eigen::OnTheRight>(l21);
        MatrixMap(update, remaining, remaining).selfadjointView<Eigen::Lower>().rankUpdate(l21, -1.0);
    }
    return -1;
}

void forward(const double* panel, std::ptrdiff_t rows, std::ptrdiff_t columns, double* x,
             double* below) {
    ConstMatrixMap front(panel, rows, columns);
    VectorMap head(x, columns);
    front.topRows(columns).triangularView<Eigen::Lower>().solveInPlace(head);
    if (rows > columns) VectorMap(below, rows - columns).noalias() = front.bottomRows(rows - columns) * head;
}

void backward(const double* panel, std::ptrdiff_t rows, std::ptrdiff_t columns, double* x,
              const double* below) {
    ConstMatrixMap front(panel, rows, columns);
    VectorMap head(x, columns);
    if (rows > columns)
        head.noalias() -= front.bottomRows(rows - columns).transpose() *
                          ConstVectorMap(below, rows - columns);
    front.topRows(columns).transpose().triangularView<Eigen::Upper>().solveInPlace(head);
}

}  // namespace

extern const SupernodeKernels kernels;
const SupernodeKernels kernels{TPSCORE_DENSE_ISA_NAME, &factor_front, &forward, &backward};

}  // namespace TPSCORE_DENSE_NAMESPACE

#if !defined(TPSCORE_DENSE_X86_64_V3)

#if defined(TPSCORE_HAVE_X86_64_V3)
namespace supernode_x86_64_v3 {
extern const SupernodeKernels kernels;
}  // namespace supernode_x86_64_v3

namespace {
bool cpu_runs_x86_64_v3() {
    __builtin_cpu_init();
#if defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
    return __builtin_cpu_supports("x86-64-v3");
#else
    // The features the compiler uses at -march=x86-64-v3 (every CPU with AVX2, FMA
    // and BMI2 also has the level's F16C, LZCNT and MOVBE).
    return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") &&
           __builtin_cpu_supports("bmi") && __builtin_cpu_supports("bmi2");
#endif
}
}  // namespace
#endif

const SupernodeKernels& supernode_kernels_baseline() {
    return supernode_baseline::kernels;
}

const SupernodeKernels& supernode_kernels() {
    static const SupernodeKernels& chosen = []() -> const SupernodeKernels& {
        // TPSCORE_SIMD=baseline (simd.hpp) keeps every hand-dispatched kernel, these
        // included, on the baseline build
        if (simd_level_lowered_to_baseline()) return supernode_baseline::kernels;
#if defined(TPSCORE_HAVE_X86_64_V3)
        if (cpu_runs_x86_64_v3()) return supernode_x86_64_v3::kernels;
#endif
        return supernode_baseline::kernels;
    }();
    return chosen;
}

#endif  // !TPSCORE_DENSE_X86_64_V3

}  // namespace tpscore
