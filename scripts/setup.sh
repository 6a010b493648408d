#!/usr/bin/env bash
# Set up openfly-agent on a fresh Linux machine (Python >= 3.10): a virtual environment with the CPU
# PyTorch stack, the package in editable mode, the torchvision start-up shim and the Mesa EGL libraries.
# Re-running it is cheap: it skips the install when nothing it depends on changed.
#   VENV=path        where the environment goes (default .venv)
#   OPENFLY_CUDA=1   install the CUDA wheels from PyPI instead of pinning the CPU torch
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-$(command -v python3.11 || command -v python3)}

# 1. Headless OpenGL (EGL through Mesa) for the embedded simulator's renderer.
if ! ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[setup] installing Mesa EGL (libegl1 libegl-mesa0 libgl1-mesa-dri)"
    apt-get update -qq && apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null
  else
    echo "[setup] WARNING: Mesa EGL not found; the embedded simulator needs it:" \
         "sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri" >&2
  fi
fi

# 2. The Python environment.
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
stamp="$VENV/.openfly-setup"
want=$(cat pyproject.toml requirements/constraints-cpu.txt scripts/_openfly_tv_shim.py | sha256sum | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want${OPENFLY_CUDA:-}" ]; then
  "$VENV/bin/python" -m pip install -q --upgrade pip
  if [ -n "${OPENFLY_CUDA:-}" ]; then
    "$VENV/bin/python" -m pip install -q -e ".[dev]"
  else
    "$VENV/bin/python" -m pip install -q -c requirements/constraints-cpu.txt -e ".[dev]"
  fi
  site=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  cp scripts/_openfly_tv_shim.py "$site/_openfly_tv_shim.py"
  echo "import _openfly_tv_shim" > "$site/openfly_tv_shim.pth"
  echo "$want${OPENFLY_CUDA:-}" > "$stamp"
fi
"$VENV/bin/python" -c "import timm, transformers, openfly_agent; print('[setup] ok: openfly_agent', openfly_agent.__version__, '| timm', timm.__version__, '| transformers', transformers.__version__)"
