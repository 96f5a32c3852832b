// Which SIMD instruction set the hand-dispatched kernels use.
//
// The dense Cholesky micro-kernels, the AVX-512 TPS evaluation and the sparse
// factorisation's supernode kernels are compiled for several x86-64 levels and pick
// one at load time from the CPU (no -march=native).
// The loops built with TPSCORE_DISPATCH follow it too.
#pragma once

// The compiler's means of building one loop for several instruction sets, in one place.
//
// TPSCORE_TARGET_V4 / _V3: one function compiled for one level (x86-64-v4: AVX-512;
// v3: AVX2 + FMA): one binary for every x86-64 CPU, no -march=native, the level
// picked at run time by simd_level() below. TPSCORE_INLINE: always inlined, so that a
// helper takes the instruction set of the function it is inlined into.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define TPSCORE_MULTI_TARGET 1
#define TPSCORE_TARGET_V4 __attribute__((target("arch=x86-64-v4")))
#define TPSCORE_TARGET_V3 __attribute__((target("arch=x86-64-v3")))
#else
#define TPSCORE_MULTI_TARGET 0
#endif

// TPSCORE_DISPATCH(NAME, (parameters), (arguments)) defines `void NAME(parameters)`
// that runs `NAME##_impl(arguments)` built for the level simd_level() picks: three
// wrappers, one per level, each with its own inlined copy of the (TPSCORE_INLINE)
// implementation, so that TPSCORE_SIMD lowers these loops as it lowers the rest.
#if TPSCORE_MULTI_TARGET
#define TPSCORE_DISPATCH(NAME, PARAMS, ARGS)                           \
    TPSCORE_TARGET_V4 void NAME##_v4 PARAMS { NAME##_impl ARGS; }      \
    TPSCORE_TARGET_V3 void NAME##_v3 PARAMS { NAME##_impl ARGS; }      \
    void NAME##_baseline PARAMS { NAME##_impl ARGS; }                  \
    void NAME PARAMS {                                                 \
        switch (::tpscore::simd_level()) {                             \
            case ::tpscore::SimdLevel::avx512: NAME##_v4 ARGS; break;  \
            case ::tpscore::SimdLevel::avx2: NAME##_v3 ARGS; break;    \
            default: NAME##_baseline ARGS;                             \
        }                                                              \
    }
#else
#define TPSCORE_DISPATCH(NAME, PARAMS, ARGS) \
    void NAME PARAMS { NAME##_impl ARGS; }
#endif

#if defined(__GNUC__)
#define TPSCORE_INLINE inline __attribute__((always_inline))
#else
#define TPSCORE_INLINE inline
#endif

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
