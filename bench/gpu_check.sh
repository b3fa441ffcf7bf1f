#!/usr/bin/env bash
# The GPU checks of this project in one call, for a GPU machine without a package registry: the
# `gpu` tests (exactness of the compiled and captured updates, the replay memory's rings on the
# GPU, a GPU checkpoint resumed on the CPU, sampling without a wait for the GPU) and
# `bench trainer_speed` on the GPU beside tmrl 0.7.1 and Stable-Baselines3 on the same GPU.
#
#   bash bench/anchors/gpu_wheels.sh        # on a machine with a registry, once: .wheels/ (git ignores it)
#   bash bench/gpu_check.sh                 # on the GPU machine, from the repository's root, .wheels/ beside
#
# Everything it writes goes to $OUT (default bench/out/gpu): summary.txt (the GPU, the versions,
# the tests' last lines, the benchmark's table), gpu_tests.txt, trainer_speed.txt, the benchmark's
# JSONL record, install.txt. The machine's python3 is used as it is (its CUDA build of PyTorch);
# this project's other dependencies go to a folder on PYTHONPATH, the anchors to folders of their
# own (bench/anchors/install_*.sh with TMRL_WHEELS). Nothing is installed into python3 itself.
#
# Settings (environment): DEVICE (default cuda), ROUNDS (3), SECS (3, per figure), CASES (pendulum,tmfull),
# TESTS_TIMEOUT (240 s), SPEED_TIMEOUT (330 s), TMRL_WHEELS (.wheels), ANCHORS (/tmp). With DEVICE=cpu it runs on a
# CPU machine too (the gpu tests then skip): the way to try the script before a GPU session.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-bench/out/gpu}
DEVICE=${DEVICE:-cuda}
ANCHORS=${ANCHORS:-/tmp}  # where tmrl 0.7.1 and SB3 go (tmrl-anchor/, sb3-anchor/: must not hold venvs already)
WHEELS=$(cd "${TMRL_WHEELS:-.wheels}" && pwd) || { echo "no wheels folder: run bench/anchors/gpu_wheels.sh first"; exit 2; }
mkdir -p "$OUT"
summary="$OUT/summary.txt"
: > "$summary"
say() { echo "$*" | tee -a "$summary"; }

say "== $(date -u +%FT%TZ) bench/gpu_check.sh at $(git rev-parse --short HEAD 2>/dev/null || echo '?'), DEVICE=$DEVICE"
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"; } | tee -a "$summary"
python3 -c "import sys, torch; print('python', sys.version.split()[0], '| torch', torch.__version__, '| cuda', torch.version.cuda, '| GPU seen:', torch.cuda.is_available())" 2>&1 | tee -a "$summary"

# Dependencies: this project's (not torch) into a folder on PYTHONPATH; the anchors' in theirs.
site=/tmp/tmrl-gpu-site
python3 -m pip install -q --no-index --no-deps --target "$site" \
    $(ls "$WHEELS"/*.whl | grep -v '/tmrl-0\.7\.1-' | grep -vE '/(stable_baselines3|numpy|packaging|typing_extensions)-') \
    > "$OUT/install.txt" 2>&1
export PYTHONPATH="$site"
TMRL_WHEELS="$WHEELS" bash bench/anchors/install_tmrl.sh "$ANCHORS"/tmrl-anchor >> "$OUT/install.txt" 2>&1
TMRL_WHEELS="$WHEELS" bash bench/anchors/install_sb3.sh "$ANCHORS"/sb3-anchor >> "$OUT/install.txt" 2>&1
say "install: $(tail -n 2 "$OUT/install.txt" | tr '\n' ' ')"

# The gpu tests: the files that hold them (collecting every test module would need packages that
# only the CI machine has: display, NATS).
files=$(grep -l "mark.gpu" tests/test_*.py | grep -v test_ci_skips)
timeout "${TESTS_TIMEOUT:-240}" python3 -m pytest -q -m gpu -p no:cacheprovider $files > "$OUT/gpu_tests.txt" 2>&1
say "gpu tests (exit $?): $(tail -n 1 "$OUT/gpu_tests.txt")"
grep -E "^(FAILED|ERROR)" "$OUT/gpu_tests.txt" | head -20 | tee -a "$summary"

# The trainer's speed, every side on the device, our memory's rings on the GPU beside the host path.
timeout "${SPEED_TIMEOUT:-330}" python3 -m bench trainer_speed --device "$DEVICE" --rounds "${ROUNDS:-3}" \
    --seconds "${SECS:-3}" --cases "${CASES:-pendulum,tmfull}" --host-memory \
    --anchor-dir "$ANCHORS"/tmrl-anchor --sb3-dir "$ANCHORS"/sb3-anchor > "$OUT/trainer_speed.txt" 2>&1
say "trainer_speed (exit $?):"
grep -v "^round " "$OUT/trainer_speed.txt" | tail -n 60 | tee -a "$summary"
record=$(sed -n 's/^results: //p' "$OUT/trainer_speed.txt")
[ -n "$record" ] && [ -f "$record" ] && cp "$record" "$OUT/"
say "== done $(date -u +%T)"
