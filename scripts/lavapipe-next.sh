#!/usr/bin/env bash
# A newer lavapipe, side-loaded: Debian sid's Mesa (26.2.6 on 2026-11-30) with its glibc and
# libraries unpacked into .lavapipe-next/, nothing installed. CI's lavapipe (Debian 12's Mesa
# 25.0) offers no cooperative matrices; Mesa 26's offers 8 × 8 × 8 tiles of f16 with f16 or
# f32 sums, so `linear_coop8` (shaders/linear_coop.wgsl) and the whole engine on a device with
# wgpu's cooperative-matrix feature run here, not first on a lent GPU.
#
#   bash scripts/lavapipe-next.sh prepare            # root: a temporary apt source for sid
#   bash scripts/lavapipe-next.sh run BINARY ARGS…   # BINARY on that lavapipe, e.g.
#       bash scripts/lavapipe-next.sh run target/release/road gpu selftest
#       bash scripts/lavapipe-next.sh run target/debug/deps/kernels-<hash> f16
#
# `run` starts BINARY through sid's dynamic loader (sid's Mesa needs glibc 2.43): a program it
# starts in turn (cargo's rustc, a test binary) gets the system's libraries, so run test
# executables directly (`cargo test --no-run` lists them).
set -euo pipefail
cd "$(dirname "$0")/.."
dir="$PWD/.lavapipe-next"
lib="$dir/root/usr/lib/x86_64-linux-gnu"

case "${1:-}" in
prepare)
    if [ "$(id -u)" -ne 0 ]; then
        echo "prepare needs root (a temporary apt source list)" >&2
        exit 2
    fi
    mkdir -p "$dir/debs"
    list=/etc/apt/sources.list.d/road-lavapipe-next.list
    echo "deb http://deb.debian.org/debian sid main" > "$list"
    trap 'rm -f "$list"; apt-get update -qq >/dev/null 2>&1 || true' EXIT
    apt-get update -qq
    # mesa-vulkan-drivers' dependencies, and libllvm22's, as sid has them.
    (cd "$dir/debs" && apt-get download -t sid mesa-vulkan-drivers libvulkan1 libc6 \
        libdisplay-info3 libdrm-amdgpu1 libdrm2 libelf1t64 libexpat1 libgcc-s1 libllvm22 \
        libpng16-16t64 libstdc++6 libwayland-client0 libx11-xcb1 libx11-6 libxcb-dri3-0 \
        libxcb-present0 libxcb-randr0 libxcb-shm0 libxcb-sync1 libxcb-xfixes0 libxcb1 libxau6 \
        libxdmcp6 libbsd0 libmd0 libxshmfence1 libzstd1 zlib1g libffi8 libedit2 libz3-4 \
        libtinfo6 liblzma5 libxml2-16 libicu78)
    for deb in "$dir"/debs/*.deb; do dpkg -x "$deb" "$dir/root"; done
    # The ICD file names the driver by the system's path: point it at the unpacked one.
    sed -i "s#\"library_path\": \"[^\"]*\"#\"library_path\": \"$lib/libvulkan_lvp.so\"#" \
        "$dir/root/usr/share/vulkan/icd.d/lvp_icd.json"
    "$0" run "${ROAD_BIN:-target/release/road}" gpu info 2>/dev/null | grep -E "adapter|cooperative|f16" || true
    ;;
run)
    shift
    if [ ! -f "$dir/root/usr/lib64/ld-linux-x86-64.so.2" ]; then
        echo "no $dir: run 'bash scripts/lavapipe-next.sh prepare' first" >&2
        exit 2
    fi
    export VK_ICD_FILENAMES="$dir/root/usr/share/vulkan/icd.d/lvp_icd.json"
    exec "$dir/root/usr/lib64/ld-linux-x86-64.so.2" --library-path "$lib" "$@"
    ;;
*)
    sed -n 2,16p "$0" >&2
    exit 2
    ;;
esac
