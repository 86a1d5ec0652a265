#!/usr/bin/env bash
# The one install path for README, CI and Docker.
# usage: scripts/install.sh [EXTRAS]   (default extras: render,synth,plot,serve,ray,test)
# PHOTOREG_TRAIN=1 also installs the `train` extra (CPU PyTorch, onnx) for photoreg.train.
# Picks the Open3D build: the CUDA one where nvidia-smi sees a GPU (or PHOTOREG_CUDA=1), else open3d-cpu.
set -euo pipefail
cd "$(dirname "$0")/.."
extras=${1:-render,synth,plot,serve,ray,test}
py=${PYTHON:-python3}

# Debian packages: libusb (open3d import), EGL/OSMesa (pyrender offscreen), LLVM 19 (Mitsuba llvm_ad_rgb).
debs="libusb-1.0-0 libgomp1 libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libllvm19"
# A system Python that is externally managed (PEP 668: Debian 12, Ubuntu 23.04+) refuses pip outside a virtual
# environment: then photoreg goes into .venv/ (python3-venv makes it), which `. scripts/activate.sh` puts on PATH.
managed=$($py -c 'import os, sys, sysconfig; print(int(sys.prefix == sys.base_prefix and os.path.exists(
    os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED"))))')
if [ "$managed" = 1 ]; then
  debs="$debs python3-venv"
fi
if command -v apt-get >/dev/null 2>&1; then
  missing=$(for d in $debs; do dpkg -s "$d" >/dev/null 2>&1 || echo "$d"; done)
  if [ -n "$missing" ]; then
    sudo=""
    if [ "$(id -u)" != 0 ]; then
      command -v sudo >/dev/null 2>&1 || { echo "install.sh: not root and no sudo; as root run: apt-get install" $missing >&2; exit 1; }
      sudo="sudo"
    fi
    $sudo apt-get update -qq
    # shellcheck disable=SC2086
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends $missing
  fi
fi

if [ "${PHOTOREG_CUDA:-}" = 1 ] || { command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; }; then
  o3d=cuda
else
  o3d=cpu
fi
# .venv/photoreg-installed marks the .venv/ this script installed into last, which scripts/activate.sh activates
if [ "$managed" = 1 ]; then
  [ -x .venv/bin/python ] || $py -m venv .venv
  touch .venv/photoreg-installed
  py=.venv/bin/python
  echo "install.sh: $($py -c 'import sys; print(sys.base_prefix)')'s Python is externally managed (PEP 668):" \
       "installing into .venv/ (. scripts/activate.sh puts it on PATH)"
else
  rm -f .venv/photoreg-installed
fi
$py -m pip install -q --upgrade pip
$py -m pip install -q -e ".[$o3d,$extras]"
# Opt-in training extra (PHOTOREG_TRAIN=1): PyTorch's CPU build from its own index, then the `train` extra.
if [ "${PHOTOREG_TRAIN:-}" = 1 ]; then
  $py -m pip install -q torch --index-url https://download.pytorch.org/whl/cpu
  $py -m pip install -q -e ".[train]"
fi
# pyrender 0.1.45 pins PyOpenGL 3.1.0, which fails under OSMesa: 3.1.10 over it.
if [[ ",$extras," == *",render,"* ]]; then
  $py -m pip install -q --no-deps "PyOpenGL==3.1.10"
fi
echo "photoreg installed (open3d: $o3d, extras: $extras)$([ "$managed" = 1 ] && echo " in .venv/")"
