#!/usr/bin/env bash
# The CUDA path on an NVIDIA machine, checked in one command (docs/gpu.md):
#   tools/gpu_check.sh                 # install into .gpu-venv/, then every check
#   tools/gpu_check.sh --skip-install  # check the current Python instead
#   tools/gpu_check.sh --dry-run       # list the steps and their commands
# Everything is written to runs/gpu-check/ (summary.json, logs/, commands.sh, env.txt).
# This wrapper finds a Python 3.10+ to run tools/gpu_check.py with (GPU_CHECK_PYTHON
# names one); that script needs only the standard library.
set -u
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
for py in ${GPU_CHECK_PYTHON:-} python3 python3.13 python3.12 python3.11 python3.10 python; do
    if command -v "$py" >/dev/null 2>&1 && "$py" -c 'import sys; sys.exit(sys.version_info < (3, 10))' 2>/dev/null; then
        exec "$py" "$here/gpu_check.py" "$@"
    fi
done
echo "gpu_check: needs Python 3.10 or newer (set GPU_CHECK_PYTHON=/path/to/python3)" >&2
exit 2
