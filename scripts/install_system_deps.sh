#!/usr/bin/env bash
# Make sure the system libraries for offscreen rendering are present:
# Mesa EGL (MUJOCO_GL=egl, the default) and OSMesa (the fallback).
# Installs them with apt-get when missing; otherwise says what to install.
set -euo pipefail

PACKAGES="libegl1 libgl1-mesa-dri libosmesa6"

have_lib() { case "$(ldconfig -p 2>/dev/null)" in *"$1"*) return 0 ;; *) return 1 ;; esac; }
have_swrast() {
  local f
  for f in /usr/lib/*/dri/swrast_dri.so /usr/lib/dri/swrast_dri.so /usr/lib64/dri/swrast_dri.so; do
    [ -e "$f" ] && return 0
  done
  return 1
}

missing() {
  have_lib 'libEGL.so.1' || return 0
  have_lib 'libOSMesa.so' || return 0
  have_swrast || return 0
  return 1
}

if ! missing; then
  exit 0
fi

if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" -eq 0 ]; then
  echo "Installing offscreen rendering libraries: $PACKAGES"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  # shellcheck disable=SC2086
  apt-get install -y -qq --no-install-recommends $PACKAGES >/dev/null
  ldconfig
  if missing; then
    echo "error: $PACKAGES installed, but libEGL/libOSMesa/swrast_dri still not found." >&2
    exit 1
  fi
  exit 0
fi

cat >&2 <<MSG
error: offscreen rendering needs Mesa's EGL and OSMesa libraries, which are missing,
and this script cannot install them (needs root and apt-get).
Install them with your system's package manager, for example:
  Debian/Ubuntu:  sudo apt-get install $PACKAGES
  Fedora:         sudo dnf install mesa-libEGL mesa-dri-drivers mesa-libOSMesa
then run the command again.
MSG
exit 1
