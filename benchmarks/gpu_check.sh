#!/usr/bin/env bash
# The GPU check in one command (docs/benchmarks.md, "GPU check"): install the package, run the
# CUDA tests and every method's batch on the GPU against the CPU, write gpu_check.md and
# gpu_check.json to OUT_DIR; all within GPU_CHECK_BUDGET_S seconds (default 290).
#
#   benchmarks/gpu_check.sh [OUT_DIR] [gpu_check.py options...]
#
# The install is the README's, except that a torch which already sees CUDA is kept (pip keeps
# any torch >= 2.1); without CUDA it installs the CPU build torch==2.13.0 as the README does.
# On a machine that cannot reach a package index the install falls back to the package alone
# (no dependencies), after installing any wheels found in .whl/ (e.g. snntorch, which the
# models' tests import: `pip download --no-deps -d .whl snntorch` where pip works). The exit
# status is gpu_check.py's: 0 when the check passed.
set -uo pipefail
cd "$(dirname "$0")/.." || exit 1
OUT=${1:-gpu-check}
[ $# -gt 0 ] && shift
BUDGET_S=${GPU_CHECK_BUDGET_S:-290}
PY=${PYTHON:-python3}
START=$(date +%s)
mkdir -p "$OUT"
LOG="$OUT/install.log"

if "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null
then
    echo "gpu_check: torch $("$PY" -c 'import torch; print(torch.__version__)') sees CUDA: kept"
    INSTALL=(-e ".[all]")
else
    echo "gpu_check: no CUDA torch here: installing the CPU build torch==2.13.0"
    INSTALL=(torch==2.13.0 -e ".[all]")
fi
if [ -d .whl ] && ls .whl/*.whl >/dev/null 2>&1; then
    "$PY" -m pip install -q --no-index --no-deps .whl/*.whl >>"$LOG" 2>&1 \
        && echo "gpu_check: installed the wheels of .whl/"
fi
# A third of the budget at most for the install; a machine without a package index fails fast.
INSTALL_S=$((BUDGET_S / 3))
if timeout "$INSTALL_S" "$PY" -m pip install -q --retries 1 --timeout 10 "${INSTALL[@]}" \
        >>"$LOG" 2>&1; then
    echo "gpu_check: installed the package and its extras"
elif timeout 60 "$PY" -m pip install -q --no-index --no-deps --no-build-isolation -e . \
        >>"$LOG" 2>&1; then
    echo "gpu_check: no package index: installed the package alone (see $LOG)"
else
    echo "gpu_check: could not install (see $LOG): running from the source tree"
fi
for module in numpy snntorch tonic pytest scipy hypothesis; do
    "$PY" -c "import $module" 2>/dev/null || echo "gpu_check: $module is missing"
done

LEFT=$((BUDGET_S - $(date +%s) + START))
if [ "$LEFT" -le 30 ]; then
    echo "gpu_check: the install took the budget ($LEFT s left)"
    exit 1
fi
# gpu_check.py keeps to what is left; the hard limit 20 s beyond is a safety net only.
timeout $((LEFT + 20)) "$PY" benchmarks/gpu_check.py --out "$OUT" --budget-s "$LEFT" "$@"
