// The CPU backend's vectorised kernels (kernel_set.inc: the rasterizer's per-tile passes,
// the projection, SSIM and resampling's vote) compiled once per x86-64 instruction set level, and the choice among them
// for the running CPU.
//
// GCC compiles vector-extension code for the target of the enclosing function, so each
// variant sits under its own `#pragma GCC target` with a vector width that the level
// handles natively (16 lanes for AVX-512, 8 for AVX2, 4 for SSE2). Other compilers and
// architectures get one variant for the build's own target.
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "kernels.h"

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define PROMPTGS_X86_VARIANTS 1
#endif
#if defined(__x86_64__) || defined(__SSE2__)
#include <immintrin.h>  // a few mask tests (any_lane); GCC declares every level's intrinsics here
#endif

#ifdef PROMPTGS_X86_VARIANTS
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wpsabi"
// GCC 12's own AVX-512 headers trip this on their undefined-source idiom (__Y = __Y).
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"

#pragma GCC push_options
#pragma GCC target("arch=x86-64-v4")
#define PROMPTGS_NS kernels_avx512
#define PROMPTGS_VW 16
#include "kernel_set.inc"
#undef PROMPTGS_NS
#undef PROMPTGS_VW
#pragma GCC pop_options

#pragma GCC push_options
#pragma GCC target("arch=x86-64-v3")
#define PROMPTGS_NS kernels_avx2
#define PROMPTGS_VW 8
#include "kernel_set.inc"
#undef PROMPTGS_NS
#undef PROMPTGS_VW
#pragma GCC pop_options

#define PROMPTGS_NS kernels_sse2
#define PROMPTGS_VW 4
#include "kernel_set.inc"
#undef PROMPTGS_NS
#undef PROMPTGS_VW

#pragma GCC diagnostic pop

#else  // one variant for the build target

#if defined(__AVX512F__)
#define PROMPTGS_VW 16
#elif defined(__AVX2__)
#define PROMPTGS_VW 8
#else
#define PROMPTGS_VW 4
#endif
#define PROMPTGS_NS kernels_native
#include "kernel_set.inc"
#undef PROMPTGS_NS
#undef PROMPTGS_VW

#endif

namespace promptgs {

namespace {

#define PROMPTGS_KERNEL_TABLE(NS, NAME)                                                                        \
    Kernels {                                                                                                   \
        {NS::forward_tile<0>, NS::forward_tile<1>, NS::forward_tile<2>, NS::forward_tile<3>,                    \
         NS::forward_tile<4>, NS::forward_tile<5>},                                                             \
            {NS::backward_tile<0, false>, NS::backward_tile<1, false>, NS::backward_tile<2, false>,             \
             NS::backward_tile<3, false>, NS::backward_tile<4, false>, NS::backward_tile<5, false>},            \
            {NS::backward_tile<0, true>, NS::backward_tile<1, true>, NS::backward_tile<2, true>,                \
             NS::backward_tile<3, true>, NS::backward_tile<4, true>, NS::backward_tile<5, true>},               \
            NS::project_forward_range, NS::project_backward_range, NS::ssim_forward_band,                       \
            NS::ssim_backward_band, NS::carve_pixels, NAME                                                      \
    }

}  // namespace

const Kernels& kernels() {
    static_assert(kMaxChannelsFixed == 5, "update PROMPTGS_KERNEL_TABLE");
    static const Kernels chosen = [] {
#ifdef PROMPTGS_X86_VARIANTS
        // PROMPTGS_SIMD=avx2 or sse2 caps the level below what the CPU supports (tests run
        // every variant's kernels this way on one machine); anything else is ignored.
        const char* cap = std::getenv("PROMPTGS_SIMD");
        const int max_level = !cap ? 4 : std::strcmp(cap, "sse2") == 0 ? 2 : std::strcmp(cap, "avx2") == 0 ? 3 : 4;
        __builtin_cpu_init();
        if (max_level >= 4 && __builtin_cpu_supports("x86-64-v4")) return PROMPTGS_KERNEL_TABLE(kernels_avx512, "avx512");
        if (max_level >= 3 && __builtin_cpu_supports("x86-64-v3")) return PROMPTGS_KERNEL_TABLE(kernels_avx2, "avx2");
        return PROMPTGS_KERNEL_TABLE(kernels_sse2, "sse2");
#else
        return PROMPTGS_KERNEL_TABLE(kernels_native, "native");
#endif
    }();
    return chosen;
}

}  // namespace promptgs
