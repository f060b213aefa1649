#!/usr/bin/env bash
# The whole test suite, from a fresh Debian/Ubuntu machine with a Rust toolchain:
# installs what the tests need (lavapipe), then formatting, clippy with -D warnings, and every
# test of the workspace. The data tests read ../shared/data/interaction (or $ROAD_DATA).
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

start=$(date +%s)
cargo fmt --all -- --check
cargo clippy --workspace --all-targets --locked -- -D warnings
cargo test --workspace --locked
echo "test suite finished in $(( $(date +%s) - start )) s"
