// Minimal fork-join over std::thread (the library links no OpenMP runtime; torch brings its own).
#pragma once

#include <cstdint>
#include <thread>
#include <vector>

#if defined(__SSE__) || defined(__x86_64__)
#include <xmmintrin.h>
#define USKERN_HAS_MXCSR 1
#endif

namespace uskern {

// Flushes denormal inputs and results to zero while alive, then restores the thread's mode. Without
// it, a few denormal intermediates (e.g. exp() near the bottom of the float range) cost microcode
// assists that made the vectorised KL loop 3x slower; values below 1.2e-38 carry no information here.
class FlushDenormals {
   public:
    FlushDenormals() {
#ifdef USKERN_HAS_MXCSR
        saved_ = _mm_getcsr();
        _mm_setcsr(saved_ | 0x8040);  // FTZ | DAZ
#endif
    }
    ~FlushDenormals() {
#ifdef USKERN_HAS_MXCSR
        _mm_setcsr(saved_);
#endif
    }
    FlushDenormals(const FlushDenormals&) = delete;
    FlushDenormals& operator=(const FlushDenormals&) = delete;

   private:
    unsigned int saved_ = 0;
};

// Runs fn(worker) for worker = 0 .. workers - 1, worker 0 on the calling thread, and waits for all;
// every worker runs with denormals flushed (FlushDenormals) unless FLUSH is false (a kernel that must give
// torch's bits: torch keeps denormals).
template <bool FLUSH = true, typename Fn>
void run_workers(int64_t workers, Fn fn) {
    auto guarded = [&fn](int64_t id) {
        if constexpr (FLUSH) {
            FlushDenormals ftz;
            fn(id);
        } else {
            fn(id);
        }
    };
    std::vector<std::thread> threads;
    threads.reserve(workers > 1 ? workers - 1 : 0);
    for (int64_t i = 1; i < workers; ++i) threads.emplace_back(guarded, i);
    guarded(int64_t{0});
    for (auto& th : threads) th.join();
}

}  // namespace uskern
