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
    # Offline (bench/anchors/offline.sh): SB3 and Gymnasium; the machine's python3 has the rest.
    . "$(cd "$(dirname "$0")" && pwd)/offline.sh"
    offline_install "$DIR" 'stable_baselines3-*' 'gymnasium-*' 'farama*'
else
    python3 -m venv "$DIR/venv"
    "$DIR/venv/bin/pip" install -q torch==2.13.0
    "$DIR/venv/bin/pip" install -q 'stable-baselines3>=2.3' gymnasium
fi
cd "$DIR"
"$DIR/venv/bin/python" -c "import stable_baselines3 as sb3; print('stable-baselines3', sb3.__version__, 'ready')"
