#include "tpscore/parallel.hpp"

#include <atomic>
#include <cstdlib>

namespace tpscore {

namespace {
std::atomic<int> requested_threads{0};

int hardware_threads() {
    const unsigned hw = std::thread::hardware_concurrency();
    return hw > 0 ? static_cast<int>(hw) : 1;
}

int default_threads() {
    if (const char* env = std::getenv("TPSCORE_NUM_THREADS")) {
        // strtol saturates instead of overflowing (atoi's overflow is undefined).
        const long n = std::strtol(env, nullptr, 10);
        if (n > 0) return static_cast<int>(std::min<long>(n, max_threads()));
    }
    return hardware_threads();
}
}  // namespace

int max_threads() { return 4 * hardware_threads(); }

int num_threads() {
    const int n = requested_threads.load(std::memory_order_relaxed);
    return std::min(n > 0 ? n : default_threads(), max_threads());
}

void set_num_threads(int n) {
    requested_threads.store(n > 0 ? std::min(n, max_threads()) : 0, std::memory_order_relaxed);
}

}  // namespace tpscore
