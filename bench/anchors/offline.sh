# Sourced by install_tmrl.sh and install_sb3.sh: their offline install (TMRL_WHEELS set), for a
# machine without a package registry (a GPU machine).
#
#   offline_install DIR WHEEL_PATTERN...
#
# installs the wheels of $TMRL_WHEELS whose names match the patterns (bench/anchors/gpu_wheels.sh
# downloads them) into DIR/site without dependencies, and writes DIR/venv/bin/python: this
# machine's python3 (its CUDA torch, numpy, pandas...) with DIR/site first on its path. No venv:
# one made from a venv's python (the GPU image's is one) would not see that venv's packages.
offline_install() {
    local dir=$1
    shift
    local wheels
    wheels=$(cd "$TMRL_WHEELS" && pwd)
    if [ -L "$dir/venv/bin/python" ]; then  # a venv made online: never write through its python's link
        echo "$dir holds a virtual environment already: give another DIR" >&2
        exit 2
    fi
    local files=()
    for pattern in "$@"; do
        files+=("$wheels"/$pattern)
    done
    python3 -m pip install -q --no-index --no-deps --target "$dir/site" "${files[@]}"
    mkdir -p "$dir/venv/bin"
    printf '#!/bin/sh\nPYTHONPATH="%s" exec "%s" "$@"\n' "$dir/site" "$(python3 -c 'import sys; print(sys.executable)')" \
        > "$dir/venv/bin/python"
    chmod +x "$dir/venv/bin/python"
}
