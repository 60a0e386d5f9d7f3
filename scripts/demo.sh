#!/usr/bin/env bash
# Sets up .venv, trains ATGS on the built-in synthetic scene (synthesized and prepared on first
# use) and renders an orbit video of the result. atgs-train ends with the held-out evaluation
# that atgs-eval gives (every frame of the test cameras; written to $OUT/eval).
# Extra arguments go to atgs-train (e.g. cpu-accurate --train.minutes 60: a preset, then flags).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh
OUT=${OUT:-runs/demo}
.venv/bin/atgs-train --out "$OUT" "$@"
.venv/bin/atgs-render "$OUT/ckpt.pt" --path orbit --out "$OUT/orbit.mp4"
echo "Done: checkpoint $OUT/ckpt.pt, metrics $OUT/eval, video $OUT/orbit.mp4; play it with: .venv/bin/atgs-view $OUT/ckpt.pt"
