#!/usr/bin/env bash
# The whole test suite, from a fresh Debian/Ubuntu machine with a Rust toolchain and Python 3:
# installs what the tests need (lavapipe; a virtual environment .venv-test with eclipse-zenoh,
# mcap, pytest and the Python client), then formatting, the module-circle check, clippy with
# -D warnings, every test of the workspace, the Python client's tests against the `road`
# binary and the scripts' own (scripts/tests). The data tests read ../shared/data/interaction
# (or $ROAD_DATA).
set -euo pipefail
cd "$(dirname "$0")/.."

if ! command -v cargo >/dev/null 2>&1; then
    echo "cargo not found: install a Rust toolchain (1.87 or newer, e.g. with rustup) first" >&2
    exit 1
fi

bash scripts/install-test-deps.sh

# Mesa complains without a runtime dir; give it a private one.
if [ -z "${XDG_RUNTIME_DIR:-}" ] || [ ! -d "${XDG_RUNTIME_DIR}" ]; then
    export XDG_RUNTIME_DIR="$(mktemp -d)"
fi
# In CI, pin the Vulkan loader to lavapipe so that results do not depend on the machine.
if [ -n "${CI:-}" ] && [ -z "${VK_ICD_FILENAMES:-}" ]; then
    icd=$(ls /usr/share/vulkan/icd.d/lvp_icd*.json | head -1)
    export VK_ICD_FILENAMES="$icd"
fi

# A fresh clone gains nothing from incremental compilation but its disk use (GBs of caches).
if [ -n "${CI:-}" ]; then
    export CARGO_INCREMENTAL=0
fi
echo "disk free for target/: $(df -h --output=avail . | tail -1 | tr -d ' ')"

start=$(date +%s)
cargo fmt --all -- --check
# No module of a crate imports another in a circle (ARCHITECTURE.md).
python3 scripts/module_cycles.py
cargo clippy --workspace --all-targets --locked -- -D warnings
cargo test --workspace --locked

# The Python client (clients/python) against a real `road serve` on loopback, and the scripts'
# own tests (scripts/tests; no PyTorch here).
if ! python3 -m venv --help >/dev/null 2>&1 || ! python3 -c 'import ensurepip' >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
    $SUDO apt-get install -y -q python3-venv
fi
if [ ! -x .venv-test/bin/python ]; then
    python3 -m venv .venv-test
fi
.venv-test/bin/pip install -q "eclipse-zenoh==1.10.2" mcap pytest
.venv-test/bin/pip install -q ./clients/python
cargo build --locked -p road-cli
ROAD_BIN="$(cargo metadata --format-version 1 --no-deps | python3 -c 'import json,sys; print(json.load(sys.stdin)["target_directory"])')/debug/road" \
    .venv-test/bin/python -m pytest -q clients/python/tests scripts/tests
echo "test suite finished in $(( $(date +%s) - start )) s"
