#include "tpscore/simd.hpp"

#include <cstdlib>
#include <cstring>

namespace tpscore {

namespace {
SimdLevel detect() {
    SimdLevel level = SimdLevel::baseline;
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("x86-64-v4"))
        level = SimdLevel::avx512;
    else if (__builtin_cpu_supports("x86-64-v3"))
        level = SimdLevel::avx2;
#endif
    if (simd_level_lowered_to_baseline()) return SimdLevel::baseline;
    const char* requested = std::getenv("TPSCORE_SIMD");
    if (requested != nullptr && std::strcmp(requested, "avx2") == 0 && level > SimdLevel::avx2)
        level = SimdLevel::avx2;
    return level;
}
}  // namespace

bool simd_level_lowered_to_baseline() {
    static const bool lowered = [] {
        const char* requested = std::getenv("TPSCORE_SIMD");
        return requested != nullptr && std::strcmp(requested, "baseline") == 0;
    }();
    return lowered;
}

SimdLevel simd_level() {
    static const SimdLevel level = detect();
    return level;
}

const char* simd_level_name(SimdLevel level) {
    switch (level) {
        case SimdLevel::avx512: return "avx512";
        case SimdLevel::avx2: return "avx2";
        default: return "baseline";
    }
}

}  // namespace tpscore
