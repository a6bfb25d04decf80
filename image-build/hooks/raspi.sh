#!/usr/bin/env bash
# mmdebstrap customize hook (Raspberry Pi builds): the Pi's kernel and boot partition (ROOT/boot/firmware) for
# BOARD (pi3-4 or pi5) on ARCH, as Debian's own Pi images have them: Debian's kernel, and raspi-firmware, whose
# kernel hook copies the kernel, initramfs and device trees to the boot partition and writes config.txt and
# cmdline.txt from /etc/default/raspi-* (hooks/boot-config.sh: the root by label and read-only, the console).
# Those are written before the kernel is installed so that its one initramfs (slow under emulation) and the boot
# files are made with them and with overlayroot's script for the read-only root. On a Pi 3 or 4 the front end's
# buses are then written into every device tree on the boot partition (device-trees.sh), SPI1 with SPI1_CS chip
# selects (1 or 3).
#
#   raspi.sh ROOT BOARD ARCH SPI1_CS
set -euo pipefail
usage="usage: raspi.sh ROOT BOARD ARCH SPI1_CS"
root=${1:?$usage}
board=${2:?$usage}
arch=${3:?$usage}
spi1_cs=${4:?$usage}
here=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=../board.sh
. "$here/board.sh"
board_build "$board" "$arch"
# A clean environment: the build machine's settings (PIP_*, PYTHON*) are not the image's.
in_root() { chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LC_ALL=C.UTF-8 \
    DEBIAN_FRONTEND=noninteractive "$@"; }

"$here/hooks/boot-config.sh" "$root" "$board"
in_root apt-get install -y -qq --no-install-recommends -o Dpkg::Options::=--force-confold \
    -t "$kernel_suite" "$kernel" raspi-firmware >/dev/null

boot=$root/boot/firmware
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
case $board in
    pi3-4)
        shopt -s nullglob
        trees=("$boot"/bcm2711-rpi-*.dtb "$boot"/bcm2837-rpi-*.dtb)
        [ ${#trees[@]} -gt 0 ] || { echo "raspi.sh: raspi-firmware put no Pi 3 or 4 device tree in $boot" >&2; exit 1; }
        dtc -@ -q -I dts -O dtb -o "$work/appliance-buses.dtbo" "$here/files/appliance-buses.dts"
        "$here/device-trees.sh" "$work/appliance-buses.dtbo" "$spi1_cs" "${trees[@]}"
        ;;
    pi5)
        # The Pi 5's firmware boots a partition only if it holds the Pi 5's device tree.
        [ -f "$boot/bcm2712-rpi-5-b.dtb" ] || { echo "raspi.sh: $kernel from $kernel_suite put no" \
                                                    "bcm2712-rpi-5-b.dtb in $boot" >&2; exit 1; }
        ;;
esac
contents=$(in_root sh -c 'lsinitramfs /boot/firmware/initrd.img-*')
for needed in scripts/init-bottom/overlayroot bin/busybox; do
    grep -q "$needed\$" <<<"$contents" ||
        { echo "raspi.sh: the initramfs lacks $needed, which the read-only root's overlay needs" >&2; exit 1; }
done
grep -q '^ro$' <<<"$(tr ' ' '\n' <"$boot/cmdline.txt")" ||
    { echo "raspi.sh: cmdline.txt does not mount the root read-only" >&2; exit 1; }
grep -q "console=$console,115200" "$boot/cmdline.txt" ||
    { echo "raspi.sh: cmdline.txt does not name the console $console" >&2; exit 1; }
