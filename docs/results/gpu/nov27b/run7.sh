#!/bin/bash
# First call (2026-11-27, second GPU session): set up as run5.sh did, then
# 1. the 8-bit images kept on the GPU (DEVICE_IMAGE_CACHE): the per-image cost before and
#    after, and that the GPU copy equals the CPU's bit for bit;
# 2. tumbler 800x600 against gsplat's step, two pairs alternating their order;
# 3. the mountain grid (3dgs, promptgs-1; seeds 0-2; 1500 steps) on CUDA.
T0=$(date +%s); el() { echo "[+$(( $(date +%s) - T0 ))s] $*"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/pkgs/*.whl || exit 1
python3 -c "import tarfile; tarfile.open('.gpu/pkgs/pycolmap_full.tar.xz').extractall('/tmp/site')" || exit 1
export PYTHONPATH=/tmp/site:$PWD
[ -e ../shared ] || ln -s "$PWD/.gpu/shared" ../shared
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
  python3 -c "import torch, numpy; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'numpy', numpy.__version__)"
  nproc; date; } > $OUT/0_env.log 2>&1
(python3 setup.py build_ext --inplace > /tmp/b.log 2>&1; echo "cpu ext rc $?") >> $OUT/0_env.log 2>&1 &
(t=$(date +%s); python3 -c "from gsplat.cuda._backend import _C; print('gsplat _C', _C)"; echo "gsplat compile $(( $(date +%s) - t )) s") >> $OUT/0_env.log 2>&1 &
wait
el built; cat $OUT/0_env.log

el "images on the device"
timeout 60 python3 - > $OUT/1_images.log 2>&1 <<'PY'
import statistics, time, torch
from promptgs_engine.data import load_colmap_scene
cams = load_colmap_scene("../shared/data/tumbler").train_cameras
same = all(torch.equal(c.load_image(device="cuda").cpu(), c.load_image()) for c in cams)
x = torch.arange(256, dtype=torch.float32)
print("views", len(cams), f"{cams[0].width}x{cams[0].height}", "gpu copy equals cpu:", same,
      "| cuda x/255 differs from cpu x/255 in", int((x.cuda() / 255.0).cpu().ne(x / 255.0).sum()), "of 256 values")
def ms(fn):
    ts = []
    for c in cams * 3:
        torch.cuda.synchronize(); t = time.perf_counter(); fn(c); torch.cuda.synchronize(); ts.append(time.perf_counter() - t)
    return 1000 * statistics.median(ts)
print("per image, median ms: cpu float then copy %.3f | uint8 on gpu, table there %.3f"
      % (ms(lambda c: c.load_image().to("cuda")), ms(lambda c: c.load_image(device="cuda"))))
PY
cat $OUT/1_images.log

el "side by side"
timeout -s INT 190 python3 benchmarks/gsplat_side_by_side.py ../shared/data/tumbler --steps 3000 --runs 2 --out $OUT/gsplat_side_by_side_tumbler800_3000 > $OUT/2_sbs.log 2>&1
tail -6 $OUT/2_sbs.log

el "mountain grid"
timeout -s INT 150 python3 -m promptgs_engine bench --scene mountain=.gpu/mountain --methods 3dgs promptgs-1 --iterations 1500 --seeds 0 1 2 --out /tmp/mg > /tmp/mg.log 2>&1; tail -3 /tmp/mg.log
cp /tmp/mg/results.jsonl $OUT/3_grid_results.jsonl 2>/dev/null
python3 -c "
import json
for l in open('/tmp/mg/results.jsonl'):
    d = json.loads(l); print({k: d.get(k) for k in ('method', 'seed', 'status', 'psnr', 'masked_psnr', 'recall', 'n_gaussians', 'train_seconds')})" 2>&1 | tee $OUT/3_grid.log
el end
