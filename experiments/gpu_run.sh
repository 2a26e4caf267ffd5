#!/usr/bin/env bash
# Everything measured on a lent GPU, in one run of at most about 9 minutes; results in $1.
#
# Prepared here (the GPU machine has no network and no ../shared):
#   echo /.whl/ >> .git/info/exclude; echo /.gpu/ >> .git/info/exclude
#   pip download --no-deps --only-binary=:all: --python-version 3.12 -d .whl trimesh==5.2.0
#   python -m kernels_ir cubins --arch sm_90 --out .gpu/cubins   # the IR's own code
#   python experiments/gpu_counts.py prepare                      # .gpu/counts.pkl
#   mkdir -p .gpu/scenes && cp -r ../shared/scenes/{conference,sibenik,manifest.json} .gpu/scenes/
# Then, on the device (carry .whl and .gpu):  bash experiments/gpu_run.sh "$OUT"
# and here:  python experiments/gpu_counts.py compare --dir <the files that came back>
#
# Steps, each with its own time limit so that one failure leaves the others' results:
#   1. the device, driver, toolkit and clocks            -> log.txt
#   2. hardware counts of each kernel on the same rays    -> measure.json, hits.npz,
#      as the replay (ncu, the IR's cubins)                  ncu_raw.csv, ncu_source.csv
#   3. the same launches timed (2 warm-up, 10 timed)      -> log.txt
#   4. the actual column, Conference camera 0 at the      -> conference_actual.csv
#      paper's 1024x768 with 32 secondary rays per hit
#   5. the GPU tests: hits judged by the float64 reference -> pytest_gpu.txt
#   6. the actual column on Sibenik                       -> sibenik_actual.csv
set -u
OUT=${1:?usage: gpu_run.sh OUTDIR}
LOG=$OUT/log.txt
export PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba_cache SIMT_SIM_SCENES=$PWD/.gpu/scenes
step() { echo "== $(date -u +%T) $*" >>"$LOG"; }

step setup
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl >>"$LOG" 2>&1
export PYTHONPATH=/tmp/site:$PWD
NCU=$(command -v ncu || ls /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -1)

step "1 environment"
{
    nvidia-smi
    nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.max.sm,clocks.mem,power.limit \
        --format=csv
    nvcc --version | tail -2
    "$NCU" --version | tail -1
    python3 -c "import cupy, numba, numpy; print('cupy', cupy.__version__, 'runtime',
cupy.cuda.runtime.runtimeGetVersion(), 'driver', cupy.cuda.runtime.driverGetVersion(),
'nvrtc', cupy.cuda.nvrtc.getVersion(), 'numba', numba.__version__, 'numpy', numpy.__version__)"
} >>"$LOG" 2>&1

step "2 hardware counts"
KERNELS='^(while_while|if_if|persistent_while_while|persistent_speculative_while_while|dynamic_fetch|speculative_dynamic_fetch|packet)$'
METRICS=smsp__inst_executed.sum,smsp__thread_inst_executed.sum,smsp__thread_inst_executed_pred_on.sum,gpu__time_duration.sum,dram__bytes_read.sum,lts__t_bytes.sum,sm__cycles_elapsed.avg.per_second
MEASURE="python3 experiments/gpu_counts.py measure --data .gpu/counts.pkl --out $OUT/measure.json --hits $OUT/hits.npz"
counts() {  # $1: seconds, $2: the cubins option, $3: the per-instruction section
    timeout "$1" "$NCU" --clock-control none -k "regex:$KERNELS" --metrics "$METRICS" $3 \
        -f -o /tmp/counts $MEASURE $2 >>"$LOG" 2>&1
}
counts 120 "--cubins .gpu/cubins" "--section SourceCounters" ||
    { step "2b without the per-instruction section"; counts 60 "--cubins .gpu/cubins" ""; } ||
    { step "2c with NVRTC's code"; counts 60 "" ""; }
"$NCU" -i /tmp/counts.ncu-rep --page raw --csv >"$OUT/ncu_raw.csv" 2>>"$LOG"
timeout 60 "$NCU" -i /tmp/counts.ncu-rep --page source --csv --print-source sass \
    >"$OUT/ncu_source.csv" 2>>"$LOG"

step "3 timed launches"
TIMED="python3 experiments/gpu_counts.py measure --data .gpu/counts.pkl --time --out /tmp/timed.json"
timeout 45 $TIMED --cubins .gpu/cubins >>"$LOG" 2>&1 || timeout 45 $TIMED >>"$LOG" 2>&1

step "4 actual column, conference"
timeout 180 python3 -m simt_sim table --scene conference --rays primary,ao,diffuse \
    --resolution 1024x768 --spp 32 --camera 0 --gpu h200 --actual --format csv \
    --out "$OUT/conference_actual.csv" >>"$LOG" 2>&1

step "5 gpu tests"
timeout 150 python3 -m pytest -q -p no:cacheprovider -m gpu tests/tracers/test_cuda_tracer.py \
    >"$OUT/pytest_gpu.txt" 2>&1

step "6 actual column, sibenik"
timeout 60 python3 -m simt_sim table --scene sibenik --rays primary,ao,diffuse \
    --resolution 1024x768 --spp 32 --camera 0 --gpu h200 --actual --format csv \
    --out "$OUT/sibenik_actual.csv" >>"$LOG" 2>&1
mv "$OUT"/*.meta.json /tmp/  # at most 8 files come back
step done
