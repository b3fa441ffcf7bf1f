#!/usr/bin/env bash
# Installs Stable-Baselines3 in a venv of its own, for the trainer-speed comparison only (never a
# dependency of this project).
#
#   bash bench/anchors/install_sb3.sh [DIR]        (default DIR: /tmp/sb3-anchor)
#   TMRL_WHEELS=.wheels bash bench/anchors/install_sb3.sh    (offline: see bench/anchors/gpu_wheels.sh)
#
# python -m bench trainer_speed finds it there by default (--sb3-python DIR/venv/bin/python
# elsewhere).
set -euo pipefail
DIR=${1:-/tmp/sb3-anchor}
if [ -n "${TMRL_WHEELS:-}" ]; then
    # Offline (a GPU machine without a package registry): SB3 and Gymnasium from the wheels of
    # bench/anchors/gpu_wheels.sh into DIR/site; DIR/venv/bin/python runs this machine's python3 (its
    # torch, numpy, pandas, matplotlib) with them. No venv: see install_tmrl.sh.
    wheels=$(cd "$TMRL_WHEELS" && pwd)
    if [ -L "$DIR/venv/bin/python" ]; then  # a venv made online: never write through its python's link
        echo "$DIR holds a virtual environment already: give another DIR" >&2
        exit 2
    fi
    python3 -m pip install -q --no-index --no-deps --target "$DIR/site" \
        "$wheels"/stable_baselines3-*.whl "$wheels"/gymnasium-*.whl "$wheels"/farama_notifications-*.whl
    mkdir -p "$DIR/venv/bin"
    printf '#!/bin/sh\nPYTHONPATH="%s" exec "%s" "$@"\n' "$DIR/site" "$(python3 -c 'import sys; print(sys.executable)')" \
        > "$DIR/venv/bin/python"
    chmod +x "$DIR/venv/bin/python"
else
    python3 -m venv "$DIR/venv"
    "$DIR/venv/bin/pip" install -q torch==2.13.0
    "$DIR/venv/bin/pip" install -q 'stable-baselines3>=2.3' gymnasium
fi
cd "$DIR"
"$DIR/venv/bin/python" -c "import stable_baselines3 as sb3; print('stable-baselines3', sb3.__version__, 'ready')"
