#!/bin/bash
# Second call: the six tests that failed with a GPU present, after their fixes, and the
# CUDA training test the first call's time box cut (promptgs-1, the GPU crop statistics).
T0=$(date +%s); el() { echo "[+$(( $(date +%s) - T0 ))s] $*"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/pkgs/*.whl || exit 1
python3 -c "import tarfile; tarfile.open('.gpu/pkgs/pycolmap_full.tar.xz').extractall('/tmp/site')" || exit 1
export PYTHONPATH=/tmp/site:$PWD
(python3 setup.py build_ext --inplace > /tmp/b.log 2>&1; echo "cpu ext rc $?" >> /tmp/b.log) &
python3 -c "from gsplat.cuda._backend import _C" > /dev/null 2>&1 &
wait
el built; tail -1 /tmp/b.log
OMP_NUM_THREADS=2 timeout -s INT -k 10 110 python3 -m pytest -n 8 -v -rfE -p no:cacheprovider \
  tests/test_distributed.py::test_world_size_one_with_nccl_is_the_single_process_trainer \
  tests/test_distributed.py::test_a_killed_rank_ends_the_run_with_one_line_and_its_checkpoint_resumes_on_one_rank \
  tests/test_distributed.py::test_failure_line_names_the_killed_rank \
  tests/test_sky.py::test_the_trainer_marks_the_background_shell_for_the_strategy \
  tests/test_train.py::test_a_far_sky_shell_starts_beside_the_sfm_points_unless_turned_off \
  tests/test_train.py::test_cli_train_eval_render_and_resume \
  tests/test_train.py::test_an_interrupted_run_resumes_to_the_same_result \
  tests/test_train_cuda.py > $OUT/5_refixed.log 2>&1
echo "rc $?"; grep -E "PASSED|FAILED|ERROR" $OUT/5_refixed.log | grep -v "^E " | sed 's/^\[gw[0-9]*\] \[ *[0-9]*%\] //' ; tail -2 $OUT/5_refixed.log
el end
