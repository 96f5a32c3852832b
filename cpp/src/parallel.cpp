#include "tpscore/parallel.hpp"

#include <atomic>
#include <cstdlib>

namespace tpscore {

namespace {
std::atomic<int> requested_threads{0};

int default_threads() {
    if (const char* env = std::getenv("TPSCORE_NUM_THREADS")) {
        const int n = std::atoi(env);
        if (n > 0) return n;
    }
    const unsigned hw = std::thread::hardware_concurrency();
    return hw > 0 ? static_cast<int>(hw) : 1;
}
}  // namespace

int num_threads() {
    const int n = requested_threads.load(std::memory_order_relaxed);
    return n > 0 ? n : default_threads();
}

void set_num_threads(int n) { requested_threads.store(n > 0 ? n : 0, std::memory_order_relaxed); }

}  // namespace tpscore
