#!/bin/bash
# Second call: the host-side changes A/B (new tree against HEAD's engine in .gpu/head).
T0=$(date +%s); el() { echo "[+$(( $(date +%s) - T0 ))s] $*"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/pkgs/*.whl || exit 1
python3 -c "import tarfile; tarfile.open('.gpu/pkgs/pycolmap_full.tar.xz').extractall('/tmp/site')" || exit 1
(python3 setup.py build_ext --inplace > /tmp/b.log 2>&1; echo "cpu ext rc $?") &
PYTHONPATH=/tmp/site python3 -c "from gsplat.cuda._backend import _C; print('gsplat _C', _C)" 2>&1 | tail -1
wait
el built
PYTHONPATH=/tmp/site:$PWD timeout 60 python3 -m pytest tests/test_train_cuda.py -q -k images -p no:cacheprovider 2>&1 | tail -3
el parity
PG="train .gpu/mountain --backend cuda --strategy promptgs --center-prompt --iterations 700 --quiet --overwrite"
G3="train .gpu/mountain --backend cuda --strategy 3dgs --no-sky --iterations 700 --quiet --overwrite"
ms() { python3 -c "import json; d=json.load(open('$1')); print('$1', round(d['ms_per_step_200_300'],2), round(d['ms_per_step_400_500_plain'],2), 'syncs/100 steps', sum(d['sync_sites_steps_300_399'].values()))"; }
PYTHONPATH=/tmp/site:$PWD timeout 60 python3 .gpu/profile_cuda.py $OUT/pg_new.json -- $PG --out /tmp/a > $OUT/pg_new.log 2>&1; ms $OUT/pg_new.json
PYTHONPATH=/tmp/site:$PWD/.gpu/head PROFILE_TABLES=0 timeout 50 python3 .gpu/profile_cuda.py /tmp/pg_old.json -- $PG --out /tmp/b > /dev/null 2>&1; ms /tmp/pg_old.json
el pg
PYTHONPATH=/tmp/site:$PWD PROFILE_TABLES=0 timeout 40 python3 .gpu/profile_cuda.py /tmp/g3_new.json -- $G3 --out /tmp/c > /dev/null 2>&1; ms /tmp/g3_new.json
PYTHONPATH=/tmp/site:$PWD/.gpu/head PROFILE_TABLES=0 timeout 40 python3 .gpu/profile_cuda.py /tmp/g3_old.json -- $G3 --out /tmp/d > /dev/null 2>&1; ms /tmp/g3_old.json
el 3dgs
PYTHONPATH=/tmp/site:$PWD PROFILE_TABLES=0 timeout 40 python3 .gpu/profile_cuda.py /tmp/pg_new2.json -- $PG --out /tmp/e > /dev/null 2>&1; ms /tmp/pg_new2.json
PYTHONPATH=/tmp/site:$PWD/.gpu/head PROFILE_TABLES=0 timeout 40 python3 .gpu/profile_cuda.py /tmp/pg_old2.json -- $PG --out /tmp/f > /dev/null 2>&1; ms /tmp/pg_old2.json
el pg2
el end
