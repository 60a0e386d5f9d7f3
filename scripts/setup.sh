#!/usr/bin/env bash
# Sets up everything ATGS needs on a fresh machine; idempotent (a second run installs nothing).
#   1. Debian/Ubuntu packages for headless OpenGL and the window test (Mesa OSMesa/EGL, Xvfb)
#      and for compiling the CPU rasterizer (g++, Python headers); with ATGS_TEST_SETUP=1 (set by
#      scripts/test.sh) also what the web player's tests run in (Chromium, Node.js): installed
#      with apt-get when missing (as root, or through passwordless sudo); otherwise one line with
#      the command to run.
#   2. .venv with torch: a CUDA build plus the optional gsplat rasterizer when an NVIDIA GPU is
#      present, else a CPU build (torch==2.13.0; from a CPU wheel index if plain pip would pick a
#      multi-GB CUDA build), then this package with its test extras.
# Environment: PYTHON (interpreter, default python3), ATGS_SKIP_APT=1 (skip step 1),
# ATGS_TORCH (a pip requirement for torch that overrides the choice, e.g. "torch==2.11.0"),
# ATGS_CUDA=0|1 (force the CPU or the GPU set-up), ATGS_TEST_SETUP=1 (also what the tests need).
set -euo pipefail
cd "$(dirname "$0")/.."

say() { echo "setup: $*" >&2; }
fail() { echo "setup: error: $*" >&2; exit 2; }

# --- 1. system packages ---------------------------------------------------------------------
PY=${PYTHON:-python3}
command -v "$PY" >/dev/null || fail "no '$PY' on PATH; install Python 3.10 or newer (apt-get install python3 python3-venv python3-dev) or set PYTHON=/path/to/python"
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else 1)' \
  || fail "$("$PY" -V 2>&1) is too old; ATGS needs Python 3.10 or newer (set PYTHON=/path/to/python3.x)"

missing_debs() {
  local need=(libosmesa6 libegl1 libgl1-mesa-dri xvfb xauth)
  command -v g++ >/dev/null || need+=(g++)
  if [ "${ATGS_TEST_SETUP:-0}" = 1 ]; then
    # the web player's tests: Debian's Chromium driven by Playwright, its JS unit tests by Node.js
    need+=(chromium)
    command -v node >/dev/null || need+=(nodejs)
  fi
  # Python headers for the C++ rasterizer extension (only a system Python lacks them; pyenv/conda ship them)
  if ! "$PY" -c 'import os, sysconfig, sys; sys.exit(0 if os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")) else 1)'; then
    need+=("python3-dev")
  fi
  local out=()
  for p in "${need[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || out+=("$p")
  done
  echo "${out[@]:-}"
}

if [ "${ATGS_SKIP_APT:-0}" != 1 ] && command -v dpkg-query >/dev/null && command -v apt-get >/dev/null; then
  MISSING=$(missing_debs)
  if [ -n "$MISSING" ]; then
    if [ "$(id -u)" = 0 ]; then SUDO=""
    elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then SUDO="sudo"
    else fail "missing Debian packages: $MISSING; run: sudo apt-get install -y $MISSING  (then run this command again)"
    fi
    say "installing Debian packages: $MISSING"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -qq || fail "apt-get update failed; run: sudo apt-get update && sudo apt-get install -y $MISSING"
    # shellcheck disable=SC2086
    $SUDO apt-get install -y -qq $MISSING >/dev/null || fail "apt-get could not install $MISSING; run: sudo apt-get install -y $MISSING"
  fi
elif [ "${ATGS_SKIP_APT:-0}" != 1 ]; then
  say "not a Debian/Ubuntu system: make sure Mesa's OSMesa/EGL, Xvfb, a C++ compiler and the Python headers are installed"
fi

# --- 2. Python environment ------------------------------------------------------------------
if [ ! -x .venv/bin/python ]; then "$PY" -m venv .venv || fail "could not create .venv with $PY (Debian: apt-get install python3-venv)"; fi
VPY=.venv/bin/python
$VPY -m pip install -q --upgrade pip

has_gpu() {
  case "${ATGS_CUDA:-}" in 1) return 0 ;; 0) return 1 ;; esac
  command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1
}

if $VPY -c 'import torch' 2>/dev/null && [ -z "${ATGS_TORCH:-}" ]; then
  : # keep the torch that is there (the CPU or CUDA build chosen on the first run)
elif [ -n "${ATGS_TORCH:-}" ]; then
  $VPY -m pip install -q "$ATGS_TORCH"
elif has_gpu; then
  say "NVIDIA GPU found: installing a CUDA build of torch and gsplat"
  $VPY -m pip install -q "torch>=2.4"
else
  # A CPU build. Plain PyPI serves Linux CUDA builds (several GB); use the CPU wheel when pip
  # can already see one (a local wheel cache), else PyTorch's CPU index.
  WHEEL=$($VPY -m pip install --dry-run --quiet --report - "torch==2.13.0" 2>/dev/null \
          | $VPY -c 'import json,sys; r=json.load(sys.stdin); print(next((i["download_info"]["url"] for i in r["install"] if i["metadata"]["name"]=="torch"), ""))' 2>/dev/null || true)
  case "$WHEEL" in
    *cpu*) $VPY -m pip install -q "torch==2.13.0" ;;
    *) say "installing the CPU build of torch from https://download.pytorch.org/whl/cpu"
       $VPY -m pip install -q "torch==2.13.0" --index-url https://download.pytorch.org/whl/cpu \
         || fail "could not install a CPU build of torch; install one yourself (.venv/bin/pip install torch) and rerun" ;;
  esac
fi

EXTRAS="test"
if $VPY -c 'import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)' 2>/dev/null; then EXTRAS="test,cuda"; fi
$VPY -m pip install -q -e ".[$EXTRAS]"
