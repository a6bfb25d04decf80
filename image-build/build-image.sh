#!/usr/bin/env bash
# Build the bed's SD-card image: Debian bookworm with the appliance, made by mmdebstrap from Debian's
# archive (README.md in this folder describes the result and how to use it).
#
#   build-image.sh [--arch arm64|amd64] [--out DIR] [--rootfs-only] [--mirror URL]
#
# DIR (default ./image-out) receives wheels/ (the Python packages), rootfs/ (the root file system) and,
# unless --rootfs-only, appliance-ARCH.img. --rootfs-only stops at the root file system, for any
# architecture; the image (Raspberry Pi partitions and firmware) is made for arm64 only.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
arch=arm64 out=./image-out rootfs_only=no mirror=http://deb.debian.org/debian
while [ $# -gt 0 ]; do
    case $1 in
        --arch) arch=${2:?--arch needs a value}; shift 2 ;;
        --out) out=${2:?--out needs a folder}; shift 2 ;;
        --rootfs-only) rootfs_only=yes; shift ;;
        --mirror) mirror=${2:?--mirror needs a URL}; shift 2 ;;
        *) echo "build-image.sh: unknown option '$1' (see the comment at the top of this script)" >&2; exit 2 ;;
    esac
done
case $arch in arm64 | amd64) ;; *) echo "build-image.sh: --arch must be arm64 or amd64, got '$arch'" >&2; exit 2 ;; esac
if [ "$rootfs_only" = no ] && [ "$arch" != arm64 ]; then
    echo "build-image.sh: the SD-card image is for the Raspberry Pi (arm64); use --rootfs-only for $arch" >&2
    exit 2
fi
# Every tool the build will need, checked before the long part starts: tool:Debian package.
tools="mmdebstrap:mmdebstrap python3:python3"
[ "$arch" != arm64 ] || tools="$tools dtc:device-tree-compiler fdtoverlay:device-tree-compiler"
[ "$rootfs_only" = yes ] || tools="$tools sfdisk:fdisk mkfs.vfat:dosfstools mcopy:mtools mkfs.ext4:e2fsprogs"
for entry in $tools; do
    command -v "${entry%%:*}" >/dev/null ||
        { echo "build-image.sh: ${entry%%:*} is needed (apt-get install ${entry##*:})" >&2; exit 2; }
done
case $arch in arm64) qemu=qemu-aarch64 ;; amd64) qemu=qemu-x86_64 ;; esac
if [ "$arch" != "$(dpkg --print-architecture)" ] && [ ! -e "/proc/sys/fs/binfmt_misc/$qemu" ]; then
    echo "build-image.sh: building for $arch here needs qemu-user-static and binfmt-support registered" \
         "with binfmt_misc (README.md in this folder says how)" >&2
    exit 2
fi
[ "$(id -u)" -eq 0 ] || { echo "build-image.sh: run as root (mmdebstrap's root mode, chroot)" >&2; exit 2; }
mkdir -p "$out"
out=$(cd "$out" && pwd)
rootfs=$out/rootfs
[ ! -e "$rootfs" ] || { echo "build-image.sh: $rootfs exists: remove it or choose another --out" >&2; exit 2; }

echo "build-image.sh: the Python packages for $arch" >&2
rm -rf "$out/wheels"
"$here/wheelhouse.sh" "$arch" "$out/wheels"

# What a bed runs: systemd, Python for the appliance's virtual environment, nginx and openssl for the
# screen's TLS, overlayroot for the read-only root (its initramfs script needs busybox's grep), the file
# systems' checkers; on arm64 the Pi's Wi-Fi firmware, and then its kernel and boot firmware
# (hooks/raspi.sh), as Debian's own Pi images have them.
packages=systemd,systemd-sysv,systemd-timesyncd,udev,dbus,kmod,iproute2,libnss-myhostname,e2fsprogs,dosfstools
packages=$packages,python3,python3-venv,nginx,openssl,ca-certificates,overlayroot,busybox
hooks=(--customize-hook="\"$here/hooks/appliance.sh\" \"\$1\" \"$out/wheels\"")
if [ "$arch" = arm64 ]; then
    packages=$packages,firmware-brcm80211
    hooks+=(--customize-hook="\"$here/hooks/raspi.sh\" \"\$1\"")
fi
hooks+=(--customize-hook="\"$here/hooks/image.sh\" \"\$1\"")

echo "build-image.sh: the root file system ($arch) in $rootfs" >&2
mmdebstrap --mode=root --variant=minbase --arch="$arch" --components=main,non-free-firmware \
    --include="$packages" --setup-hook='mkdir -p "$1/boot/firmware"' "${hooks[@]}" \
    bookworm "$rootfs" "deb $mirror bookworm main non-free-firmware" \
    "deb $mirror bookworm-updates main non-free-firmware" \
    "deb http://security.debian.org/debian-security bookworm-security main non-free-firmware"

if [ "$rootfs_only" = no ]; then
    "$here/assemble-image.sh" "$rootfs" "$out/appliance-$arch.img"
fi
