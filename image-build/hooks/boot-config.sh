#!/usr/bin/env bash
# The Raspberry Pi's boot settings for BOARD (pi3-4 or pi5) in the root file system ROOT: /etc/default/raspi-firmware
# and raspi-extra-cmdline, from which raspi-firmware's kernel hook writes the boot partition's cmdline.txt and
# config.txt (hooks/raspi.sh). Written before the kernel is installed, so its one initramfs and the boot files
# are made with them.
set -euo pipefail
root=${1:?usage: boot-config.sh ROOT BOARD}
board=${2:?usage: boot-config.sh ROOT BOARD}
here=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=../board.sh
. "$here/board.sh"
board_build "$board" arm64
mkdir -p "$root/etc/default"
sed "s/@CONSOLE@/$console/" "$here/files/raspi-firmware" >"$root/etc/default/raspi-firmware"
chmod 0644 "$root/etc/default/raspi-firmware"
install -m 0644 "$here/files/raspi-extra-cmdline" "$root/etc/default/raspi-extra-cmdline"
