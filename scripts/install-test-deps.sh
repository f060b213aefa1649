#!/usr/bin/env bash
# Installs what the test suite needs on a Debian/Ubuntu machine: Mesa's software Vulkan driver
# (lavapipe) and the Vulkan loader, and openssl. Prefers Mesa 25 from bookworm-backports where that suite is
# reachable (Debian 12), else the distribution's Mesa. Idempotent; needs root (or sudo).
set -euo pipefail

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

# openssl makes the certificates of the TLS deployment test (tests/deploy.rs).
if ! command -v openssl >/dev/null 2>&1; then
    $SUDO apt-get update -q && $SUDO apt-get install -y -q openssl
fi

have_lavapipe() {
    ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 && ldconfig -p | grep -q 'libvulkan.so.1'
}

if have_lavapipe; then
    echo "lavapipe already installed: $(ls /usr/share/vulkan/icd.d/lvp_icd*.json)"
    exit 0
fi

export DEBIAN_FRONTEND=noninteractive
. /etc/os-release
if [ "${VERSION_CODENAME:-}" = "bookworm" ]; then
    if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
        echo "deb http://deb.debian.org/debian bookworm-backports main" | $SUDO tee /etc/apt/sources.list.d/bookworm-backports.list >/dev/null
    fi
    $SUDO apt-get update -q
    if $SUDO apt-get install -y -q -t bookworm-backports mesa-vulkan-drivers libvulkan1; then
        echo "installed Mesa from bookworm-backports"
        exit 0
    fi
    echo "bookworm-backports unavailable; falling back to the distribution's Mesa" >&2
else
    $SUDO apt-get update -q
fi
$SUDO apt-get install -y -q mesa-vulkan-drivers libvulkan1
