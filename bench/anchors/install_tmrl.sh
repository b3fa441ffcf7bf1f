#!/usr/bin/env bash
# Installs the original tmrl 0.7.1 in a venv of its own, for the side-by-side benchmarks only
# (never a dependency of this project).
#
#   bash bench/anchors/install_tmrl.sh [DIR]        (default DIR: /tmp/tmrl-anchor)
#   TMRL_WHEELS=.wheels bash bench/anchors/install_tmrl.sh   (offline: see bench/anchors/gpu_wheels.sh)
#
# The benchmarks then run it as `HOME=DIR/home DIR/venv/bin/python ...` (python -m bench finds
# it there by default; --anchor-dir DIR elsewhere), so it never touches your ~/TmrlData.
# Why not `pip install tmrl==0.7.1`: its wheel requires pywin32, which does not install on Linux,
# so it is installed without dependencies and its runtime dependencies are listed here. Its first
# import downloads resources unless a TmrlData/config/config.json exists: tmrl-0.7.1-config.json
# beside this script is that file (the original's default TM20FULL config).
set -euo pipefail
DIR=${1:-/tmp/tmrl-anchor}
here=$(cd "$(dirname "$0")" && pwd)
if [ -n "${TMRL_WHEELS:-}" ]; then
    # Offline (bench/anchors/offline.sh): tmrl 0.7.1 and what its runtime needs beyond a
    # scientific Python, without dependencies (tmrl 0.7.1's own would ask for pywin32).
    . "$here/offline.sh"
    offline_install "$DIR" 'tmrl-0.7.1-*' 'rtgym-*' 'tlspyo-*' 'twisted-*' 'automat-*' 'constantly-*' \
        'hyperlink-*' 'incremental-*' 'zope*' 'pyopenssl-*' 'cryptography-*' 'cffi-*' 'pycparser-*' \
        'service_identity-*' 'pyasn1*' 'pyinstrument-*' 'chardet-*' 'mss-*' 'gymnasium-*' 'farama*'
else
    python3 -m venv "$DIR/venv"
    "$DIR/venv/bin/pip" install -q torch==2.13.0
    "$DIR/venv/bin/pip" install -q --no-deps tmrl==0.7.1
    "$DIR/venv/bin/pip" install -q numpy pandas gymnasium 'rtgym>=0.13' pyyaml requests \
        opencv-python-headless pyinstrument 'tlspyo>=0.2.5' chardet packaging mss wandb
fi
mkdir -p "$DIR/home/TmrlData/"{checkpoints,config,dataset,reward,weights}
cp "$here/tmrl-0.7.1-config.json" "$DIR/home/TmrlData/config/config.json"
cd "$DIR"  # outside any checkout of this project, so that `import tmrl` finds 0.7.1
HOME="$DIR/home" "$DIR/venv/bin/python" -c "import tmrl, rtgym; print('tmrl 0.7.1 ready:', tmrl.__file__)"
