#!/usr/bin/env bash
# Set up everything the project needs on a fresh Debian machine: system libraries, then a virtual
# environment at .venv/ with the project installed in editable mode. Safe to rerun.
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d needs libusb and libgomp; the bridge's renderer needs EGL with Mesa (llvmpipe) or a GPU driver
packages="libusb-1.0-0 libgomp1 libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1"
need_apt=()
for lib in libusb-1.0.so.0 libgomp.so.1 libEGL.so.1 libEGL_mesa.so.0 libgbm.so.1; do
  ldconfig -p 2>/dev/null | grep -q "$lib" || need_apt+=("$lib")
done
# the play page's tests drive Debian's Chromium (Playwright never downloads a browser here)
[ -x /usr/bin/chromium ] || { need_apt+=(chromium); packages="$packages chromium"; }
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $packages >/dev/null
  else
    echo "bootstrap: missing ${need_apt[*]}; run: sudo apt-get install $packages" >&2
    exit 1
  fi
fi

# The interpreter: Debian's CPython 3.11 where it is installed with its venv module (built with profile-guided and
# link-time optimisation, it runs the test suite's Python about a tenth faster than a default source build such as
# pyenv's: docs/testing.md), else the first python3 on PATH.
python=python3
if [ -x /usr/bin/python3.11 ] && /usr/bin/python3.11 -c "import ensurepip, venv" >/dev/null 2>&1; then
  python=/usr/bin/python3.11
fi

stamp=.venv/.bootstrap-$(sha256sum pyproject.toml | cut -c1-16)
if [ ! -f "$stamp" ]; then
  [ -x .venv/bin/python ] || "$python" -m venv .venv
  # The CPU build of torch, through pip, which finds the file of it on this machine's disk; a bare "torch"
  # requirement would pull a multi-GB CUDA build.
  log=.venv/bootstrap.log
  .venv/bin/pip install "torch==2.13.0" >"$log" 2>&1 || { cat "$log"; exit 1; }
  # The rest through uv, which resolves the same versions as pip and installs them about ten times faster
  # (docs/testing.md); torch, installed above, already satisfies every requirement on it. pip where uv can't be had.
  if .venv/bin/pip install "uv==0.13.9" >>"$log" 2>&1; then
    .venv/bin/uv pip install --python .venv/bin/python -e ".[dev]" >>"$log" 2>&1 || { cat "$log"; exit 1; }
  else
    .venv/bin/pip install -e ".[dev]" >>"$log" 2>&1 || { cat "$log"; exit 1; }
  fi
  .venv/bin/python -c "import marionette, open3d, av, prefect, torch, moderngl, numba, uvicorn, playwright"
  rm -f .venv/.bootstrap-*
  touch "$stamp"
fi
