#!/usr/bin/env bash
# Install the Debian libraries the Python wheels need at import time, when they are missing:
#   libusb-1.0-0 (open3d's wheel links it), and with --browser, chromium (report screenshot tests).
# Needs root (or sudo); otherwise it says what to install and exits 0 so a user can do it by hand.
set -u
want=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || want+=(libusb-1.0-0)
if [ "${1:-}" = "--browser" ] && ! command -v chromium >/dev/null 2>&1; then want+=(chromium); fi
[ ${#want[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
  echo "system-deps: please install: ${want[*]} (no apt-get here)" >&2; exit 0
fi
SUDO=""
if [ "$(id -u)" != 0 ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then SUDO=sudo
  else echo "system-deps: please run: sudo apt-get install -y ${want[*]}" >&2; exit 0; fi
fi
echo "system-deps: installing ${want[*]}" >&2
$SUDO apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${want[@]}" >/dev/null
