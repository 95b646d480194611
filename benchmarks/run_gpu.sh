#!/usr/bin/env bash
# The throughput benchmarks on an accelerator machine whose Python already has JAX with a GPU back-end,
# diffrax, equinox, optax, lineax, SciPy and numba (obsjax itself is used from this checkout).  Each
# writes its table as <name>_gpu.md beside the CPU one (benchmarks/results/, or $OBSJAX_BENCH_RESULTS),
# in order of importance, each within its own time limit so that one overrun leaves the others:
#   (g) the numba Dormand–Prince comparison (issue 16, item 2) at 4096 and 32768 trajectories;
#   (j) forward- and reverse-mode gradients of tune on Chen & Yen's example (item 3);
#   (a) Chen & Yen throughput against SciPy and a hand-written lax.scan;
#   (k) a batch of plants (a plant per trajectory) on the masked loop, monte_carlo and tune over plants.
# Usage: bash benchmarks/run_gpu.sh   (PYTHON=... to choose the interpreter)
set -u
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
PY=${PYTHON:-python3}
nvidia-smi -L || true
$PY -c "import jax, diffrax, equinox, numba; print('jax', jax.__version__, jax.devices(), 'diffrax', diffrax.__version__, 'equinox', equinox.__version__, 'numba', numba.__version__)" || exit 1
status=0
# ONLY="k" (a list of the letters g j a k) runs those alone
want() { [ -z "${ONLY:-}" ] || [[ " $ONLY " == *" $1 "* ]]; }
run() {
    local limit=$1; shift
    local t0=$SECONDS
    timeout "$limit" $PY "$@" || { echo "FAILED or over ${limit} s (rc $?): $*"; status=1; }
    echo "== $* took $((SECONDS - t0)) s"
}
want g && run "${G_LIMIT:-210}" benchmarks/g_numba_dopri5.py --batch 4096 32768 --repeat 5 --threads default
want j && run "${J_LIMIT:-180}" benchmarks/j_forward_gradient.py --chen-yen-only --repeat 5
want a && run "${A_LIMIT:-130}" benchmarks/a_chen_yen_throughput.py --scipy 12
want k && run "${K_LIMIT:-200}" benchmarks/k_plant_uncertainty.py
exit $status
