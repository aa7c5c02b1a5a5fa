#!/bin/bash
# The GPU checklist's open items in one call (2026-11-27): the killed-rank fix and the CUDA
# training tests, the toy scene's CPU/GPU PSNR over seeds (test_train_cuda[3dgs]'s 1.01 dB),
# PromptGS's centre prompt against 3DGS on tumbler, tumbler 800x600 against gsplat's step
# (pairs alternating their order), and the mountain grid on CUDA. Each step time-boxed.
T0=$(date +%s); el() { echo "[+$(( $(date +%s) - T0 ))s] $*"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/pkgs/*.whl || exit 1
python3 -c "import tarfile; tarfile.open('.gpu/pkgs/pycolmap_full.tar.xz').extractall('/tmp/site')" || exit 1
export PYTHONPATH=/tmp/site:$PWD
[ -e ../shared ] || ln -s "$PWD/.gpu/shared" ../shared
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__)"
  nproc; date; git log --oneline -1 2>/dev/null; } > $OUT/0_env.log 2>&1
el setup
S='import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], sys.argv[3], "psnr %.3f n %d" % (d["psnr"], d["n_gaussians"]))'
toy_cpu() {  # the CPU half of the toy probe runs while gsplat compiles
  python3 setup.py build_ext --inplace > /tmp/b.log 2>&1; echo "cpu ext rc $?"
  python3 -c "
from pathlib import Path; import hashlib
from promptgs_engine.bench.toy_scene import ToySceneConfig, make_toy_scene
p = make_toy_scene(Path('/tmp/toyt'), ToySceneConfig(width=128, height=96, focal=110.0, n_views=16, ground_grid=60, n_sfm_points=1500))
h = hashlib.md5(); [h.update(f.read_bytes()) for f in sorted(p.rglob('*')) if f.is_file()]; print('toy md5', h.hexdigest())"
  for s in 0 1 2 3; do OMP_NUM_THREADS=4 python3 -m promptgs_engine train /tmp/toyt --out /tmp/toy_cpu$s --iterations 150 --backend cpu --strategy 3dgs --seed $s --quiet > /dev/null 2>&1
    python3 -c "$S" /tmp/toy_cpu$s/metrics.json cpu $s; done; }
toy_cpu > $OUT/1_toy.log 2>&1 &
(t=$(date +%s); python3 -c "from gsplat.cuda._backend import _C; print('gsplat _C', _C)"; echo "gsplat compile $(( $(date +%s) - t )) s") >> $OUT/0_env.log 2>&1 &
wait
el built; cat $OUT/0_env.log
for s in 0 1 2 3; do python3 -m promptgs_engine train /tmp/toyt --out /tmp/toy_gpu$s --iterations 150 --backend cuda --strategy 3dgs --seed $s --quiet > /dev/null 2>&1
  python3 -c "$S" /tmp/toy_gpu$s/metrics.json cuda $s; done >> $OUT/1_toy.log 2>&1
cat $OUT/1_toy.log

el tests
OMP_NUM_THREADS=2 timeout -s INT -k 10 100 python3 -m pytest -n 8 -v -rfE -p no:cacheprovider \
  tests/test_distributed.py::test_a_killed_rank_ends_the_run_with_one_line_and_its_checkpoint_resumes_on_one_rank \
  tests/test_distributed.py::test_failure_line_names_the_killed_rank \
  tests/test_distributed.py::test_world_size_one_with_nccl_is_the_single_process_trainer \
  tests/test_render_cuda.py tests/test_train_cuda.py > $OUT/2_tests.log 2>&1
echo "rc $?"; grep -E "PASSED|FAILED|ERROR" $OUT/2_tests.log | grep -v "^E " | sed 's/^\[gw[0-9]*\] \[ *[0-9]*%\] //'; tail -2 $OUT/2_tests.log

el "tumbler bench"
timeout 90 python3 -m promptgs_engine bench --scene tumbler=../shared/data/tumbler@images_4 --methods 3dgs promptgs-center --iterations 1500 --seeds 0 --out /tmp/tb > /tmp/tb.log 2>&1; tail -3 /tmp/tb.log
cp /tmp/tb/results.jsonl $OUT/3_tumbler_bench_results.jsonl 2>/dev/null
python3 -c "
import json
for l in open('/tmp/tb/results.jsonl'):
    d = json.loads(l); print({k: d.get(k) for k in ('method', 'seed', 'status', 'psnr', 'n_gaussians', 'train_seconds')})"

el "side by side"
timeout -s INT 215 python3 benchmarks/gsplat_side_by_side.py ../shared/data/tumbler --steps 3000 --runs 3 --out /tmp/sbs/gsplat_side_by_side_tumbler800_3000 > $OUT/4_sbs.log 2>&1
cp /tmp/sbs/*.json /tmp/sbs/*.png $OUT/ 2>/dev/null; cat $OUT/4_sbs.log | tail -6

el "mountain grid"
timeout -s INT 175 python3 -m promptgs_engine bench --scene mountain=.gpu/mountain --methods 3dgs promptgs-1 --iterations 1500 --seeds 0 1 2 --out /tmp/mg > /tmp/mg.log 2>&1; tail -3 /tmp/mg.log
cp /tmp/mg/results.jsonl $OUT/5_grid_results.jsonl 2>/dev/null
python3 -c "
import json
for l in open('/tmp/mg/results.jsonl'):
    d = json.loads(l); print({k: d.get(k) for k in ('method', 'seed', 'status', 'psnr', 'masked_psnr', 'recall', 'n_gaussians', 'train_seconds')})"
el end
