#!/usr/bin/env bash
# GPU check of the batched torch/kornia tracker (issues 16 and 26, "GPU path"): on a machine with CUDA,
# runs bench/bench_torch_tracker.py with --device cuda (which measures, in the same run and on the same
# synthetic clip, decoding alone, the CPU tracker and track_batch on the GPU, speed and NME against the
# clip's true points) and again with --device cpu (CPU torch), and prints the card, the ratios and the
# NMEs. Prints figures, asserts nothing; run it from anywhere:
#
#     bash bench/gpu_check.sh                 # FRAMES=300 BATCH=64 PASSES=3 PYTHON=python3 by default
#     FRAMES=600 BATCH=128 bash bench/gpu_check.sh
#
# Without a CUDA GPU it stops within seconds, saying so (exit status 3); without torch/kornia and no
# way to install the keyshape[torch] extra, exit status 2. Logs go to $OUT (when set, e.g. on a lent
# device machine) or to a temporary folder.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
FRAMES=${FRAMES:-300}
BATCH=${BATCH:-64}
PASSES=${PASSES:-3}
LOGS=${OUT:-$(mktemp -d)}
mkdir -p "$LOGS"

# no NVIDIA driver: nothing to measure, and nothing worth installing
if ! command -v nvidia-smi >/dev/null || ! nvidia-smi -L >/dev/null 2>&1; then
    echo "gpu_check: no NVIDIA GPU here (nvidia-smi missing or finds no card): no GPU figures"
    exit 3
fi
if ! "$PY" -c "import torch, kornia" 2>/dev/null; then
    echo "gpu_check: torch/kornia missing: installing the keyshape[torch] extra"
    "$PY" -m pip install -q --retries 0 --timeout 20 -e ".[torch]" || {
        echo "gpu_check: could not install keyshape[torch] (offline?): no GPU figures"; exit 2; }
fi
"$PY" - <<'EOF'
import sys
import torch
if not torch.cuda.is_available():
    print(f"gpu_check: torch {torch.__version__} sees no CUDA GPU (built for CUDA {torch.version.cuda}): "
          "no GPU figures")
    sys.exit(3)
p = torch.cuda.get_device_properties(0)
print(f"card: {p.name}, {p.total_memory / 2**30:.0f} GiB; torch {torch.__version__}, CUDA {torch.version.cuda}")
EOF
nvidia-smi --query-gpu=name,driver_version,clocks.max.sm --format=csv,noheader || true

for dev in cuda cpu; do
    echo "== bench_torch_tracker.py --device $dev --frames $FRAMES --batch $BATCH --passes $PASSES"
    PYTHONPATH=. "$PY" bench/bench_torch_tracker.py --device "$dev" --frames "$FRAMES" --batch "$BATCH" \
        --passes "$PASSES" | tee "$LOGS/torch_tracker_$dev.txt"
done

"$PY" - "$LOGS" <<'EOF'
import re
import sys
from pathlib import Path

def figures(path):
    text = Path(path).read_text()
    get = lambda pat: float(re.search(pat, text).group(1))
    return {"decode": get(r"decode only: (\d+) frames/s"),
            "cpu_tracker": get(r"CPU tracker \(decode \+ track\): (\d+) frames/s"),
            "batch": get(r"track_batch \(decode \+ batched track\): (\d+) frames/s"),
            "read_cpu": get(r"CPU loop (\d+) frames/s"), "read_batch": get(r"read_batch (\d+) frames/s"),
            "diff": get(r"max \|difference\| ([0-9.e+-]+) px"),
            "nme_cpu": get(r"NME vs truth: CPU ([0-9.]+)"),
            "nme_batch": get(r"NME vs truth: CPU [0-9.]+, track_batch ([0-9.]+)")}

logs = Path(sys.argv[1])
g, c = figures(logs / "torch_tracker_cuda.txt"), figures(logs / "torch_tracker_cpu.txt")
print("== summary (each line's figures from one run of the bench)")
print(f"GPU track_batch {g['batch']:.0f} frames/s: {g['batch'] / g['decode']:.2f} of decoding alone "
      f"({g['decode']:.0f}/s), {g['batch'] / g['cpu_tracker']:.2f}x the CPU tracker ({g['cpu_tracker']:.0f}/s)")
print(f"CPU torch track_batch {c['batch']:.0f} frames/s: {c['batch'] / c['decode']:.2f} of decoding alone, "
      f"{c['batch'] / c['cpu_tracker']:.2f}x the CPU tracker (GPU / CPU torch across the two runs: "
      f"{g['batch'] / c['batch']:.1f}x)")
print(f"reading only: GPU read_batch {g['read_batch'] / g['read_cpu']:.2f}x the CPU loop, "
      f"max |difference| {g['diff']:.2e} px (target 0.05 px); CPU torch {c['read_batch'] / c['read_cpu']:.2f}x, "
      f"{c['diff']:.2e} px")
print(f"NME vs the clip's true points (inter-ocular): CPU tracker {g['nme_cpu']:.4f}, track_batch on the GPU "
      f"{g['nme_batch']:.4f}, on CPU torch {c['nme_batch']:.4f}")
print(f"the issue's bar, track_batch on the GPU >= 5x the CPU tracker: "
      f"{'met' if g['batch'] >= 5 * g['cpu_tracker'] else 'not met'} ({g['batch'] / g['cpu_tracker']:.2f}x)")
EOF
echo "logs in $LOGS"
