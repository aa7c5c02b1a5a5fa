// Function multiversioning for the hot tile loops: on x86-64 with GCC the loops are
// compiled for AVX-512 (one 16-pixel tile row per vector), AVX2 and baseline SSE2, and
// the best one for the running CPU is picked at load time. Elsewhere (or with
// -DPROMPTGS_NO_CLONES) they are compiled once for the build's target.
#pragma once

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__) && \
    !defined(PROMPTGS_NO_CLONES)
#define PROMPTGS_SIMD_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define PROMPTGS_SIMD_CLONES
#endif
