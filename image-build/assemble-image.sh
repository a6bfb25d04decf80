#!/usr/bin/env bash
# The SD-card image IMG from the root file system ROOTFS (build-image.sh), with no mounting:
# each partition is made as a file (mkfs.vfat + mcopy, mkfs.ext4 -d) and written into its place.
#
#   1  APPBOOT  FAT32  256 MiB   /boot/firmware: the Pi's firmware, kernel, initramfs, config.txt,
#                                cmdline.txt, and the installer's appliance-setup.toml
#   2  APPROOT  ext4   the root file system, mounted read-only under a RAM overlay
#   3  APPDATA  ext4   DATA_MIB (default 1024) at /data: the monitor's store, calibration, configuration
#
# ROOTFS is taken apart on the way (its /boot/firmware and /data become partitions 1 and 3).
set -euo pipefail
rootfs=${1:?usage: assemble-image.sh ROOTFS IMG}
img=${2:?usage: assemble-image.sh ROOTFS IMG}
data_mib=${DATA_MIB:-1024}
boot_mib=256
start_mib=4                         # the first partition's offset, on an erase-block boundary
for tool in sfdisk mkfs.vfat mcopy mkfs.ext4; do
    command -v "$tool" >/dev/null || { echo "assemble-image.sh: $tool is needed (fdisk, dosfstools, mtools," \
                                          "e2fsprogs)" >&2; exit 2; }
done
[ -f "$rootfs/boot/firmware/config.txt" ] || { echo "assemble-image.sh: $rootfs/boot/firmware has no config.txt:" \
                                                    "not a Raspberry Pi root file system" >&2; exit 2; }
parts=$(mktemp -d "$(dirname "$img")/parts.XXXXXX")
trap 'rm -rf "$parts"' EXIT

# Partitions 1 and 3 get their folders' contents; the root keeps the empty mount points.
mkdir "$parts/boot" "$parts/data"
mv "$rootfs/boot/firmware"/* "$parts/boot/"
mv "$rootfs/data"/* "$parts/data/"
cp "$(dirname "$0")/appliance-setup.example.toml" "$parts/boot/"

# The root: its files plus a quarter, and 64 MiB for the file system's own tables.
root_mib=$(( $(du -s --block-size=1M "$rootfs" | cut -f1) * 5 / 4 + 64 ))
mkfs.vfat -F 32 -n APPBOOT -C "$parts/boot.fat" $(( boot_mib * 1024 )) >/dev/null
MTOOLS_SKIP_CHECK=1 mcopy -s -p -i "$parts/boot.fat" "$parts/boot"/* ::/
mkfs.ext4 -q -F -L APPROOT -d "$rootfs" "$parts/root.ext4" "${root_mib}M"
mkfs.ext4 -q -F -L APPDATA -d "$parts/data" "$parts/data.ext4" "${data_mib}M"

total_mib=$(( start_mib + boot_mib + root_mib + data_mib ))
rm -f "$img"
truncate -s "${total_mib}M" "$img"
sfdisk -q "$img" <<TABLE
label: dos
start=${start_mib}MiB, size=${boot_mib}MiB, type=c, bootable
size=${root_mib}MiB, type=83
size=${data_mib}MiB, type=83
TABLE
offset=$start_mib
for part in boot.fat:$boot_mib root.ext4:$root_mib data.ext4:$data_mib; do
    dd if="$parts/${part%%:*}" of="$img" bs=1M seek="$offset" conv=notrunc,sparse status=none
    offset=$(( offset + ${part##*:} ))
done
echo "assemble-image.sh: $img ($total_mib MiB):" >&2
sfdisk -l "$img" >&2
