#!/usr/bin/env bash
# Downloads, on a machine with a package registry, every wheel that a GPU machine without one needs
# to run bench/gpu_check.sh: this project's dependencies, tmrl 0.7.1's and Stable-Baselines3's,
# all but torch (the GPU machine's own CUDA build of PyTorch is used).
#
#   bash bench/anchors/gpu_wheels.sh [DIR] [PYTHON_VERSION]    (default: .wheels 3.12)
#
# DIR should be a folder git ignores (.wheels is in .gitignore), so that it can travel with the
# working tree without being committed. About 10 MB.
set -euo pipefail
DIR=${1:-.wheels}
PY=${2:-3.12}
mkdir -p "$DIR"
# --no-deps with the closure written out: a resolver would pull a CUDA torch (gigabytes) for SB3.
pip download -q --no-deps --only-binary=:all: --python-version "$PY" \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 -d "$DIR" \
    gymnasium farama-notifications cloudpickle typing-extensions \
    twisted automat constantly hyperlink incremental zope.interface attrs idna \
    pyOpenSSL cryptography cffi pycparser service-identity pyasn1 pyasn1-modules safetensors \
    stable-baselines3 rtgym pyinstrument chardet mss pytest pytest-timeout pluggy iniconfig packaging \
    tmrl==0.7.1
# tlspyo is published as a source archive only: build its (pure Python) wheel here.
pip wheel -q --no-deps -w "$DIR" tlspyo
ls "$DIR" | wc -l | xargs echo "wheels in $DIR:"
du -sh "$DIR"
