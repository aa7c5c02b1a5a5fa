#!/bin/bash
# Second call, on the machine still warm from run5.sh (its gsplat build and packages in
# /tmp kept): the side-by-side that run5.sh's 600 s limit cut, two pairs.
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx PYTHONPATH=/tmp/site:$PWD
[ -e ../shared ] || ln -s "$PWD/.gpu/shared" ../shared
timeout -s INT 200 python3 benchmarks/gsplat_side_by_side.py ../shared/data/tumbler --steps 3000 --runs 2 --out $OUT/gsplat_side_by_side_tumbler800_3000 2>&1 | tee $OUT/4_sbs.log
