#!/bin/bash
# The second and third calls of 2026-11-27's second GPU session, as they were run (one
# line each there), on the machine still warm from run7.sh.
# Call 2 (carry: .gpu/fern only). The scene data of the first call (.gpu/shared) was not
# kept on the machine, so ../shared pointed nowhere and every test that reads tumbler or
# fern skipped; the Blender test files were left out (no bpy wheel reaches the machine).
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/tx PYTHONPATH=/tmp/site:$PWD OMP_NUM_THREADS=2
[ -e ../shared ] || ln -s "$PWD/.gpu/shared" ../shared
ln -sfn "$PWD/.gpu/fern/fern" .gpu/shared/data/fern
python3 setup.py build_ext --inplace > /tmp/b2.log 2>&1
timeout -s INT -k 10 330 python3 -m pytest -q -n 16 -rfEs -p no:cacheprovider --ignore tests/test_blender_addon.py \
  --ignore tests/test_blender_train.py --ignore tests/test_blender_readers.py > $OUT/4_suite.log 2>&1
# Call 3 (carry: .gpu/shared, .gpu/fern): the data tests, stopped by their 110 s box.
ln -sfn "$PWD/.gpu/shared" ../shared; ln -sfn "$PWD/.gpu/fern/fern" .gpu/shared/data/fern
timeout -s INT -k 5 110 python3 -m pytest -q -n 16 -rfE -p no:cacheprovider tests/test_data.py tests/test_train.py > $OUT/5_data_tests.log 2>&1
