// Time spent in each stage of the C++ passes, summed over calls since the last reset: wall
// time, and the CPU time of the calling thread (with one thread, the work itself, whatever
// else the machine runs).
//
// Read from Python with _C.stage_times() (benchmarks/train_profile.py, rasterizer.py) to
// say where a training step's time goes; the cost is four clock reads per stage and call.
#pragma once

#include <omp.h>
#include <time.h>

namespace promptgs {

enum Stage {
    kStageProjectForward,
    kStageProjectBackward,
    kStageSort,         // depth keys and the radix sort of the visible Gaussians
    kStageBin,          // tile ranges, counting and filling the tile lists
    kStageGather,       // depth-ordered copies of the Gaussian data
    kStageBlendForward,
    kStageBlendBackward,
    kStageReduce,       // per-thread gradient buffers summed back to Gaussian order
    kStageCount
};

inline const char* stage_name(int s) {
    static const char* names[kStageCount] = {"project_forward", "project_backward", "sort",         "bin",
                                             "gather",          "blend_forward",    "blend_backward", "reduce"};
    return names[s];
}

// [0]: wall seconds per stage, [1]: CPU seconds of the calling thread per stage.
inline double (*stage_seconds())[kStageCount] {
    static double seconds[2][kStageCount] = {};
    return seconds;
}

inline double thread_cpu_seconds() {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

// Adds the time from construction to destruction (or stop()) to one stage.
class StageTimer {
   public:
    explicit StageTimer(Stage s) : stage_(s), wall0_(omp_get_wtime()), cpu0_(thread_cpu_seconds()) {}
    ~StageTimer() { stop(); }
    void stop() {
        if (stopped_) return;
        stage_seconds()[0][stage_] += omp_get_wtime() - wall0_;
        stage_seconds()[1][stage_] += thread_cpu_seconds() - cpu0_;
        stopped_ = true;
    }

   private:
    Stage stage_;
    double wall0_, cpu0_;
    bool stopped_ = false;
};

}  // namespace promptgs
