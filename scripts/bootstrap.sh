#!/usr/bin/env bash
# Installs the system packages flownav needs to build and test, on Debian/Ubuntu; idempotent.
#   libclang-dev           v4l's bindgen generates V4L2 bindings at build time
#   mesa-vulkan-drivers    lavapipe, a software Vulkan GPU, so the wgpu tests run without a GPU
#   libvulkan1             the Vulkan loader
#   build-essential        zstd/lz4 C code inside the MCAP writer
# and the Rust target thumbv7em-none-eabihf (Cortex-M4F/M7F), which CI builds the no_std FNP/1
# crate for.
set -euo pipefail
pkgs=(libclang-dev mesa-vulkan-drivers libvulkan1 build-essential pkg-config)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "bootstrap: installing ${missing[*]}" >&2
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi
# Tolerant: without rustup (a distribution's Rust) or offline, only the firmware-target build is missing.
if command -v rustup >/dev/null 2>&1; then
  if ! rustup target list --installed 2>/dev/null | grep -qx thumbv7em-none-eabihf; then
    echo "bootstrap: adding the Rust target thumbv7em-none-eabihf" >&2
    rustup target add thumbv7em-none-eabihf >/dev/null 2>&1 \
      || echo "bootstrap: warning: could not add thumbv7em-none-eabihf; the FNP/1 firmware-target build will fail" >&2
  fi
else
  echo "bootstrap: warning: no rustup; add the thumbv7em-none-eabihf target to build the FNP/1 crate for Cortex-M" >&2
fi
# Vulkan loaders complain without a runtime dir; give them a private one.
if [ -z "${XDG_RUNTIME_DIR:-}" ]; then
  echo "bootstrap: note: export XDG_RUNTIME_DIR=/tmp/xdg-\$(id -u) (mode 0700) to silence Vulkan warnings" >&2
fi
