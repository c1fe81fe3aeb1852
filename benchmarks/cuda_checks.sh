#!/usr/bin/env bash
# The CUDA checks of one GPU session, in the order of what matters most, each under its own
# time limit so that one slow part cannot take the rest with it:
#
#   bash benchmarks/cuda_checks.sh [OUT_DIR [PART ...]]   (needs a CUDA GPU)
#
# OUT_DIR defaults to runs/cuda-checks; PART numbers (0-8) pick the parts to run and their
# order (default all, in order), e.g. "0 2 4" and then "3 1 5" in two calls where one call
# may not take them all.
#
# 1. the CUDA tests (pytest -m cuda: captured steps, the read-free rope projection in a
#    graph, the fused solver on CUDA);
# 2. simulation of 4096 scenes of every task as simulate chooses (cuda_graph="auto"), a
#    first and a second call, then Rope's and Rope-D400's rows step by step and graphed;
# 3. launches and synchronisations per step;
# 4. the Rope training step with the reading and the read-free projection
#    (diffcontact.systems.rollout._projects_read_free decides which one a step on CUDA takes);
# 5. where a graphed step's GPU time goes;
# 6. how Rope-D400's step-by-step time grows along its rollout, selected and padded, and
#    the interior-point iterations of its projection problems (rollout_growth;
#    benchmarks/README.md, 2026-11-27, fourth sitting);
# 7. the ropes' rows of part 2 and the Rope training step of part 4 with the projection's
#    J J^T (and, for Rope-D400, the contact impulse's products) from the rows' entries
#    (--sparse-gram-cuda; the CPU's default since the fifth and sixth sittings of
#    2026-11-27, not yet CUDA's), to compare with those parts;
# 8. what sets a fused launch's time (benchmarks/run.py chain: the whole call, without the
#    interior point's problems, those alone; per layout of the solver's scratch memory),
#    then BP5 and BD5 simulated with each layout (--warp-scratch): the test of the lead of
#    benchmarks/README.md's eleventh sitting of 2026-11-28, prepared without a GPU.
#
# Each part's output goes to OUT_DIR/<part>.txt; the elapsed time is printed per part.
# The first Warp solve on a device compiles the kernels (minutes) unless the kernel cache
# (WARP_CACHE_PATH) holds them: part 0 does that once, timed on its own.
set -u
OUT=${1:-runs/cuda-checks}
shift $(($# > 0 ? 1 : 0))
PARTS=${*:-0 1 2 3 4 5 6 7 8}
for number in $PARTS; do
    if [[ $number != [0-8] ]]; then
        echo "cuda_checks.sh: unknown part $number (parts are 0-8)" >&2
        exit 2
    fi
done
mkdir -p "$OUT"
PY=${PYTHON:-python3}
start=$(date +%s)
part() {  # part NAME SECONDS COMMAND... (NAME starts with the part's number)
    local name=$1 limit=$2
    shift 2
    echo "== $name (limit ${limit}s)"
    timeout "$limit" "$@" >"$OUT/$name.txt" 2>&1
    local rc=$?
    tail -n 25 "$OUT/$name.txt"
    echo "== $name: exit $rc, t=$(($(date +%s) - start))s"
}
if ! $PY -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" 2>/dev/null; then
    echo "cuda_checks.sh: no CUDA device available to $PY (set PYTHON=...)" >&2
    exit 2
fi
part_0() {
    part 0_first_solve 300 $PY -c "
import time, torch
from diffcontact.contact import SolverSettings, solve_cone_qp
for dtype in (torch.float64, torch.float32):
    t = time.perf_counter()
    A = torch.eye(4, dtype=dtype, device='cuda').expand(8, 4, 4)
    b = -torch.ones(8, 4, dtype=dtype, device='cuda')
    mu = torch.ones(8, 2, dtype=dtype, device='cuda')
    solve_cone_qp(A, b, mu, 2, settings=SolverSettings(backend='warp'))
    torch.cuda.synchronize()
    print('first Warp solve on CUDA', dtype, round(time.perf_counter() - t, 1), 's')
"
}
part_1() { part 1_pytest_cuda 240 $PY -m pytest -q -m cuda -p no:cacheprovider; }
part_2() {
    part 2_simulate_4096 240 $PY benchmarks/run.py simulate --device cuda --all-tasks \
        --scenes 4096 --cuda-graph auto --again
    part 2_simulate_ropes 240 $PY benchmarks/run.py simulate --device cuda --all-tasks \
        --scenes 4096 --tasks Rope Rope-D400 --cuda-graph both --again
}
part_3() { part 3_launches 150 $PY benchmarks/run.py launches --device cuda; }
part_4() {
    part 4_train_rope 150 $PY benchmarks/run.py train --device cuda --tasks Rope BP5 \
        --against none --reps 3
    part 4_train_rope_read_free 150 $PY benchmarks/run.py train --device cuda --tasks Rope \
        --against none --reps 3 --read-free-projection
}
part_5() {
    part 5_profile_step 150 $PY benchmarks/run.py profile_step --device cuda --tasks BP5 BD5 Rope
}
part_6() {
    part 6_rollout_growth 200 $PY benchmarks/run.py rollout_growth --device cuda --task Rope-D400 \
        --scenes 4096 --first 3
}
part_7() {
    part 7_simulate_ropes_sparse 240 $PY benchmarks/run.py simulate --device cuda --all-tasks \
        --scenes 4096 --tasks Rope Rope-D400 --cuda-graph both --again --sparse-gram-cuda
    part 7_train_rope_sparse 200 $PY benchmarks/run.py train --device cuda --tasks Rope \
        --against none --reps 3 --sparse-gram-cuda
    part 7_train_rope_sparse_read_free 200 $PY benchmarks/run.py train --device cuda \
        --tasks Rope --against none --reps 3 --sparse-gram-cuda --read-free-projection
}
part_8() {
    part 8_chain 200 $PY benchmarks/run.py chain --device cuda
    for layout in strided contiguous matrices; do
        part "8_simulate_bp5_bd5_$layout" 120 $PY benchmarks/run.py simulate --device cuda \
            --all-tasks --tasks BP5 BD5 --scenes 4096 --again --warp-scratch "$layout"
    done
}
for number in $PARTS; do "part_$number"; done
echo "cuda_checks.sh: done in $(($(date +%s) - start))s; outputs in $OUT"
