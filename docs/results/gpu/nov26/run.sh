#!/bin/bash
# The GPU checklist's remaining items in one call. Every step time-boxed; logs in $OUT.
T0=$(date +%s); el() { echo "[+$(( $(date +%s) - T0 ))s] $*"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/pkgs/*.whl || exit 1
python3 -c "import tarfile; tarfile.open('.gpu/pkgs/pycolmap_full.tar.xz').extractall('/tmp/site')" || exit 1
export PYTHONPATH=/tmp/site:$PWD
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__)"
  nproc; date; } > /tmp/0_env.log 2>&1
el setup
(python3 setup.py build_ext --inplace > /tmp/0_build_cpu.log 2>&1; echo "cpu ext rc $?" >> /tmp/0_build_cpu.log) &
(t=$(date +%s); python3 -c "from gsplat.cuda._backend import _C; print('gsplat _C', _C)"; echo "gsplat compile $(( $(date +%s) - t )) s") >> /tmp/0_env.log 2>&1 &
wait
el built; tail -2 /tmp/0_build_cpu.log; cat /tmp/0_env.log
timeout 60 python3 -m pytest tests/test_render_cuda.py -q -rA -p no:cacheprovider 2>&1 | tail -8 
el "profile"
P="train .gpu/mountain --backend cuda --strategy 3dgs --no-sky --iterations 700 --quiet --overwrite"
timeout 60 python3 .gpu/profile_cuda.py $OUT/profile.json -- $P --out /tmp/prof > $OUT/profile.log 2>&1
tail -32 $OUT/profile.log
cp promptgs_engine/train.py /tmp/train_new.py
for k in 1 2; do
  cp /tmp/train_new.py promptgs_engine/train.py
  PROFILE_TABLES=0 timeout 40 python3 .gpu/profile_cuda.py /tmp/ab_new_$k.json -- $P --out /tmp/ab > /dev/null 2>&1
  cp .gpu/train_head.py promptgs_engine/train.py
  PROFILE_TABLES=0 timeout 40 python3 .gpu/profile_cuda.py /tmp/ab_old_$k.json -- $P --out /tmp/ab > /dev/null 2>&1
done
cp /tmp/train_new.py promptgs_engine/train.py
for f in /tmp/ab_*.json; do echo "$f $(python3 -c "import json,sys; d=json.load(open('$f')); print(d['ms_per_step_200_300'], d['ms_per_step_400_500_plain'])")"; done 
el "grid"
timeout 270 python3 -m promptgs_engine bench --scene mountain=.gpu/mountain --methods 3dgs promptgs-1 --iterations 1500 --seeds 0 1 2 --out /tmp/grid > $OUT/grid.log 2>&1
cp /tmp/grid/results.jsonl $OUT/grid_results.jsonl; tail -20 $OUT/grid.log
el "side by side"
timeout 120 python3 benchmarks/gsplat_side_by_side.py .gpu/mountain --steps 1500 --runs 2 --out /tmp/sbs/gsplat_side_by_side_mountain_1500 > /tmp/sbs.log 2>&1
cp /tmp/sbs/*.json /tmp/sbs/*.png $OUT/ 2>/dev/null; tail -14 /tmp/sbs.log
el "train tests"
timeout $(( 560 - ($(date +%s) - T0) )) python3 -m pytest tests/test_train_cuda.py -q -rA -p no:cacheprovider -x > $OUT/train_cuda.log 2>&1
tail -8 $OUT/train_cuda.log
el end
