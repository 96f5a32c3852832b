// Which SIMD instruction set the hand-dispatched kernels use.
//
// The dense Cholesky micro-kernels, the AVX-512 TPS evaluation and the sparse
// factorisation's supernode kernels are compiled for several x86-64 levels and pick
// one at load time from the CPU (no -march=native).
// The loops built with GCC's target_clones pick theirs the same way, through the
// dynamic loader, and are not affected by the override below.
#pragma once

namespace tpscore {

enum class SimdLevel : int { baseline = 0, avx2 = 1, avx512 = 2 };

/// The widest level this CPU runs (x86-64-v4: AVX-512; v3: AVX2 and FMA), lowered by
/// the environment variable TPSCORE_SIMD ("avx2" or "baseline") if it is set when the
/// level is first asked for: the tests use it to run the narrower kernels on a wider
/// CPU. Never raised above what the CPU runs.
SimdLevel simd_level();

/// Whether TPSCORE_SIMD=baseline asked for the baseline kernels (read once; true
/// whatever the CPU runs). Kernels whose wider builds this header's detection does
/// not cover (the supernode kernels' x86-64-v3 build) follow it too.
bool simd_level_lowered_to_baseline();

/// "avx512", "avx2" or "baseline".
const char* simd_level_name(SimdLevel level);

}  // namespace tpscore
