#!/usr/bin/env bash
# One lent GPU, one run: what each chapter's `full` preset costs on it, then, in the time
# left, a short full-scale image run with its linear probe. Prepared and tested on a CPU
# (--cpu-smoke) so that the device minutes are spent measuring, not debugging.
#
#   research/benchmarks/gpu_session.sh [--budget SECONDS] [--data DIR] [--cpu-smoke]
#
#   --budget     wall seconds for the whole session (default 480). Every part runs under
#                `timeout` within what is left, so one that hangs or fails leaves the others
#                their time, and the image run gets what the benchmarks did not use.
#   --data       a folder with CIFAR-10 for the image run (cifar10-jpeg.tar.gz or the official
#                archive; data/README.md). Default: $EBJEPA_DATA, else build/gpu_data/, else
#                ../shared/data/. A machine without a network needs it carried in.
#   --cpu-smoke  the same parts on the CPU with tiny settings (batch 2, one step, the ci
#                image preset): about three minutes on 2 cores, to test this script.
#
# Installs nothing. Python: $PYTHON, else .venv/bin/python (`make setup`), else python3 (a GPU
# image's own torch), with this checkout first on PYTHONPATH. It checks first that the package
# imports and names what is missing (kornia is the one dependency a bare GPU image may lack).
# Output: $OUT if set, else build/gpu_session/: session.log (everything) and summary.txt (the
# figures, one parseable line per part). The image run's encoder goes to build/gpu_session/.
set -u

budget=480 smoke=0 data=${EBJEPA_DATA:-}
while (( $# )); do
    case $1 in
        --budget) budget=$2; shift 2 ;;
        --data) data=$2; shift 2 ;;
        --cpu-smoke|--dry-run) smoke=1; shift ;;
        -h|--help) sed -n '2,/^set -u/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
        *) echo "unknown argument: $1 (see --help)" >&2; exit 2 ;;
    esac
done

root=$(cd "$(dirname "$0")/../.." && pwd)
cd "$root" || exit 1
out=${OUT:-build/gpu_session}
work=build/gpu_session  # the encoder (too big to come back from a lent machine) and part logs
rm -rf "$work/parts"  # no figure of an earlier session is read as this one's
mkdir -p "$out" "$work/parts"
log=$out/session.log summary=$out/summary.txt
: > "$summary"
: > "$log"
exec > >(tee -a "$log") 2>&1
tee_pid=$!
trap 'exec >&- 2>&-; wait "$tee_pid"' EXIT  # the log is whole before the script returns

if [[ -z ${PYTHON:-} ]]; then
    PYTHON=python3
    [[ -x .venv/bin/python ]] && PYTHON=.venv/bin/python
fi
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 TQDM_MININTERVAL=10
if [[ -z $data ]]; then
    for candidate in build/gpu_data ../shared/data; do
        [[ -d $candidate ]] && { data=$candidate; break; }
    done
fi
[[ -n $data ]] && export EBJEPA_DATA=$data

if (( smoke )); then  # the CPU of a laptop or CI machine: tiny batches, one thread
    export OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE
    bench=(--device cpu --threads 1 --batch 2 --steps 1 --warmup 1)
    image=(--scale ci) image_reserve=60 min_steps=4 max_steps=20
else  # the preset's batch, a few steps; the image run's probe and start-up need ~100 s
    bench=(--steps 5 --warmup 2)
    image=(--scale full) image_reserve=100 min_steps=300 max_steps=58500
fi

part() {  # part NAME SECONDS COMMAND...: COMMAND under timeout, at most SECONDS and the budget
    local name=$1 limit=$2 started=$SECONDS rc
    shift 2
    (( limit > budget - SECONDS )) && limit=$(( budget - SECONDS ))
    if (( limit < 10 )); then
        echo "== $name: skipped, the budget is spent"
        return 124
    fi
    local command="$*"
    echo "== $name (at most ${limit} s): ${command%%$'\n'*}"  # its first line
    timeout --kill-after=10 "$limit" "$@" 2>&1 | tee "$work/parts/$name.log"
    rc=${PIPESTATUS[0]}
    echo "== $name: exit $rc after $(( SECONDS - started )) s$( (( rc == 124 )) && echo ', timed out')"
    return "$rc"
}

last_line() {  # the parseable line a part printed last (empty if it printed none)
    grep -E "$2" "$work/parts/$1.log" 2>/dev/null | tail -n 1
}

field() {  # field NAME LINE: the value of NAME=value in LINE, or nan
    local value
    value=$(tr ' ' '\n' <<<"$2" | sed -n "s/^$1=//p" | tail -n 1)
    echo "${value:-nan}"
}

echo "gpu session $(date -u +%FT%TZ), budget ${budget} s, $( (( smoke )) && echo CPU smoke || echo GPU), python $PYTHON, data ${EBJEPA_DATA:-data/}"

part environment 60 bash -c '
    if command -v nvidia-smi >/dev/null; then nvidia-smi; else echo "no nvidia-smi"; fi
    "$0" -c "
import os, torch
print(\"torch\", torch.__version__, \"cuda\", torch.version.cuda, \"available\",
      torch.cuda.is_available(), \"cores\", os.cpu_count(), \"threads\", torch.get_num_threads())
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    print(p.name, f\"{p.total_memory / 2**30:.0f} GiB sm_{p.major}{p.minor}\",
          p.multi_processor_count, \"SMs bf16\", torch.cuda.is_bf16_supported(),
          \"cudnn\", torch.backends.cudnn.version())
"' "$PYTHON"

if ! part imports 120 "$PYTHON" -c "
import ebjepa_tutorial.training.image, ebjepa_tutorial.training.video
import ebjepa_tutorial.training.world, research.train_image
import torch
assert torch.cuda.is_available() or $smoke, 'no CUDA device: this session is for a GPU (or --cpu-smoke)'
"; then
    echo "the package does not import here, or there is no GPU (above: which). This script"
    echo "installs nothing: run 'make setup' where there is a network, or put the missing"
    echo "package's wheel (e.g. kornia and kornia_rs) on PYTHONPATH. Stopping."
    exit 1
fi

# -- each chapter's full preset, its own process: a hang or an out-of-memory stops one part --
device=nan times=""
for chapter in image sigreg video world; do
    part "bench_$chapter" 90 "$PYTHON" -m research.benchmarks.full_scale --only "$chapter" "${bench[@]}"
    found=$(last_line "bench_$chapter" '^device=')
    [[ -n $found ]] && device=$(field device "$found")
    times+=" ${chapter}_s_per_step=$(field "${chapter}_s_per_step" "$found")"
done
line="device=$device$times"  # full_scale.py's last line, one chapter from each part
echo "$line" >> "$summary"
# the world model trains in float32: would TF32 matrix products (a one-line switch) help?
part bench_world_tf32 60 "$PYTHON" -m research.benchmarks.full_scale --only world "${bench[@]}" \
    --matmul-precision high
tf32=$(last_line bench_world_tf32 '^device=')
echo "world_tf32_s_per_step=$(field world_s_per_step "$tf32")" >> "$summary"

# -- a short run of the full image preset, sized to the time left, then its linear probe -----
seconds=$(field image_s_per_step "$line")
available=$(( budget - SECONDS - image_reserve ))
steps=$("$PYTHON" -c "
import math, sys
s, available, least, most = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
fits = int(available / s) if math.isfinite(s) and s > 0 else 0
print(min(most, fits) if fits >= least else 0)
" "$seconds" "$available" "$min_steps" "$max_steps")
warmup=$(( steps / 30 > 0 ? steps / 30 : 1 ))  # the paper's 10 of 300 epochs
if (( steps > 0 )) && "$PYTHON" -c "
import sys
from ebjepa_tutorial.data.cifar10 import find_cifar10
from ebjepa_tutorial.data.paths import data_dir
sys.exit(0 if find_cifar10(data_dir()) else 'no CIFAR-10 in ' + str(data_dir()))
"; then
    echo "image run: $steps steps (warm-up $warmup) at ${seconds} s a step fit in ${available} s"
    rm -f "$work/image_run.pt" "$work/image_run.partial"  # a fresh run, not a resumed one
    part image_run $(( budget - SECONDS )) "$PYTHON" -m research.train_image \
        "${image[@]}" --steps "$steps" --warmup-steps "$warmup" --out "$work/image_run.pt"
    echo "image_run: $(last_line image_run '^saved ' | sed 's/^saved [^:]*: //')" >> "$summary"
else
    echo "image run skipped: steps=$steps (${available} s left at ${seconds} s a step), or no CIFAR-10"
    echo "image_run: skipped" >> "$summary"
fi

echo "== summary (${SECONDS} s of ${budget} s)"
cat "$summary"
