#!/bin/bash
# The player's GPU checks in one prepared run (issue 40), for a session lent a GPU machine:
#
#   bench/gpu_player.sh CKPT [CKPT ...]      # results and logs into $OUT (default /tmp/gpu_player)
#
# 1. the GL and CUDA tests of the player (decode, sort, render, packing, sorting on CUDA);
# 2. bench/gpu.py on the GPU: random Gaussians (stress rows, with drawn, splat area, overdraw),
#    each checkpoint with --decode torch (content) and --decode gl (content_gl), 1920x1080;
# 3. the real window under Xvfb with NVIDIA's GLX, when the machine has Xvfb (bench/viewer_window.py).
# Merge the results here with: python bench/gpu.py --merge $OUT/gpu.json
# The project's Python packages must be importable (see docs/gpu.md for carrying wheels).
set -u
OUT=${OUT:-/tmp/gpu_player}
mkdir -p "$OUT"
cd "$(dirname "$0")/.."
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader >"$OUT/gpu.txt" 2>&1
python3 -m pytest -q -p no:cacheprovider tests/test_viewer_gl_decode.py tests/test_viewer_gl_sort.py \
    tests/test_viewer_render.py tests/test_viewer_packing.py tests/test_viewer_sorting.py \
    tests/test_viewer_device.py >"$OUT/tests.log" 2>&1
echo "tests rc=$?" >>"$OUT/gpu.txt"
python3 bench/gpu.py --parts viewer content content_gl --devices cuda --checkpoints "$@" \
    --docs None --out "$OUT/gpu.json" >"$OUT/bench.log" 2>&1
echo "bench rc=$?" >>"$OUT/gpu.txt"
if command -v xvfb-run >/dev/null; then
    for ckpt in "$@"; do
        for decode in torch gl; do
            __GLX_VENDOR_LIBRARY_NAME=nvidia xvfb-run -a -s "-screen 0 1920x1080x24" \
                python3 bench/viewer_window.py --checkpoint "$ckpt" --size 1920x1080 --decode $decode \
                --docs None --out "$OUT/window_$(basename "$(dirname "$ckpt")")_$decode.json" >>"$OUT/window.log" 2>&1
            echo "window $ckpt $decode rc=$?" >>"$OUT/gpu.txt"
        done
    done
fi
cat "$OUT/gpu.txt"
