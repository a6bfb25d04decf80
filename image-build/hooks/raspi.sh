#!/usr/bin/env bash
# mmdebstrap customize hook (arm64): the Raspberry Pi's kernel and boot partition (ROOT/boot/firmware),
# as Debian's own Pi images have them: linux-image-arm64, and raspi-firmware, whose kernel hook copies the
# kernel, initramfs and device trees to the boot partition and writes config.txt and cmdline.txt from
# /etc/default/raspi-*. Those settings are the appliance's (the root by label and read-only, the front
# end's buses), written before the kernel is installed so that its one initramfs (slow under emulation)
# and the boot files are made with them and with overlayroot's script for the read-only root.
set -euo pipefail
root=${1:?usage: raspi.sh ROOT}
files=$(cd "$(dirname "$0")/../files" && pwd)
# A clean environment: the build machine's settings (PIP_*, PYTHON*) are not the image's.
in_root() { chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LC_ALL=C.UTF-8 \
    DEBIAN_FRONTEND=noninteractive "$@"; }

for name in raspi-firmware raspi-firmware-custom raspi-extra-cmdline; do
    install -m 0644 "$files/$name" "$root/etc/default/$name"
done
mkdir -p "$root/boot/firmware/overlays"
overlay=$root/boot/firmware/overlays/appliance-spi.dtbo
dtc -@ -q -I dts -O dtb -o "$overlay" "$files/appliance-spi.dts"
in_root apt-get install -y -qq --no-install-recommends -o Dpkg::Options::=--force-confold \
    linux-image-arm64 raspi-firmware >/dev/null

# The SPI overlay applied offline to every Raspberry Pi device tree the kernel ships, so a tree it does
# not fit stops the build instead of a bed's boot.
checked=$(mktemp)
trap 'rm -f "$checked"' EXIT
for tree in "$root"/usr/lib/linux-image-*/broadcom/bcm2*-rpi-*.dtb; do
    fdtoverlay -i "$tree" -o "$checked" "$overlay" || { echo "raspi.sh: the SPI overlay does not fit $tree" >&2; exit 1; }
done
contents=$(in_root sh -c 'lsinitramfs /boot/firmware/initrd.img-*')
for needed in scripts/init-bottom/overlayroot bin/busybox; do
    grep -q "$needed\$" <<<"$contents" ||
        { echo "raspi.sh: the initramfs lacks $needed, which the read-only root's overlay needs" >&2; exit 1; }
done
grep -q '^ro$' <<<"$(tr ' ' '\n' <"$root/boot/firmware/cmdline.txt")" ||
    { echo "raspi.sh: cmdline.txt does not mount the root read-only" >&2; exit 1; }
