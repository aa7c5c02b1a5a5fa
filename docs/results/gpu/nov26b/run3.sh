#!/bin/bash
# The GPU checklist's open items in one call (2026-11-26, second session): the whole suite
# with a GPU present, torchrun with NCCL, PromptGS against 3DGS on tumbler (time ratio on
# CUDA with the current code), tumbler 800x600 against gsplat's step. Each step time-boxed.
T0=$(date +%s); el() { echo "[+$(( $(date +%s) - T0 ))s] $*"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/pkgs/*.whl || exit 1
python3 -c "import tarfile; tarfile.open('.gpu/pkgs/pycolmap_full.tar.xz').extractall('/tmp/site')" || exit 1
export PYTHONPATH=/tmp/site:$PWD
[ -e ../shared ] || ln -s "$PWD/.gpu/shared" ../shared
ls ../shared/data
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__)"
  nproc; date; } > $OUT/0_env.log 2>&1
el setup
(python3 setup.py build_ext --inplace > /tmp/b.log 2>&1; echo "cpu ext rc $?" >> /tmp/b.log) &
(t=$(date +%s); python3 -c "from gsplat.cuda._backend import _C; print('gsplat _C', _C)"; echo "gsplat compile $(( $(date +%s) - t )) s") >> $OUT/0_env.log 2>&1 &
wait
el built; tail -1 /tmp/b.log; cat $OUT/0_env.log

el suite
OMP_NUM_THREADS=1 timeout -s INT -k 20 215 python3 -m pytest -n 14 -v -rfE -p no:cacheprovider --durations=12 \
  --ignore=tests/test_blender_addon.py --ignore=tests/test_blender_train.py --ignore=tests/test_blender_readers.py \
  > $OUT/1_suite.log 2>&1
echo "suite rc $?"; grep -E "FAILED|ERROR" $OUT/1_suite.log | grep -v "^\[gw" | head -20; tail -4 $OUT/1_suite.log

el torchrun
python3 -c "from pathlib import Path; from promptgs_engine.bench.toy_scene import make_toy_scene; make_toy_scene(Path('/tmp/toy'))" > /dev/null 2>&1
S='import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[1], {k: d[k] for k in d if not isinstance(d[k], (dict, list))}, d.get("test"))'
{ timeout 40 python3 -m torch.distributed.run --nproc-per-node 1 -m promptgs_engine train /tmp/toy --backend cuda --iterations 300 --quiet --out /tmp/tr_nccl
  timeout 30 python3 -m promptgs_engine train /tmp/toy --backend cuda --iterations 300 --quiet --out /tmp/tr_plain
  python3 -c "$S" /tmp/tr_nccl/metrics.json; python3 -c "$S" /tmp/tr_plain/metrics.json; } > $OUT/2_torchrun.log 2>&1
tail -4 $OUT/2_torchrun.log

el "tumbler bench"
timeout 80 python3 -m promptgs_engine bench --scene tumbler=../shared/data/tumbler@images_4 --methods 3dgs promptgs-center --iterations 1500 --seeds 0 --out /tmp/tb > $OUT/3_tumbler_bench.log 2>&1
cp /tmp/tb/results.jsonl $OUT/3_tumbler_bench_results.jsonl 2>/dev/null
python3 -c "
import json
for l in open('/tmp/tb/results.jsonl'):
    d = json.loads(l); print({k: d.get(k) for k in ('method', 'seed', 'status', 'psnr', 'n_gaussians', 'train_seconds', 'steps')})
" 2>&1 | tail -3

el "side by side"
timeout -s INT 150 python3 benchmarks/gsplat_side_by_side.py ../shared/data/tumbler --steps 3000 --runs 2 --out /tmp/sbs/gsplat_side_by_side_tumbler800_3000 > $OUT/4_sbs.log 2>&1
cp /tmp/sbs/*.json /tmp/sbs/*.png $OUT/ 2>/dev/null; tail -8 $OUT/4_sbs.log
el end
