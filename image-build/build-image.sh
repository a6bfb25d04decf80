#!/usr/bin/env bash
# Build the bed's SD-card image: Debian with the appliance, made by mmdebstrap from Debian's archive (README.md in
# this folder describes the builds and how to use them).
#
#   build-image.sh [--board pi3-4|pi5] [--arch arm64|armhf|amd64] [--profile NAME] [--out DIR] [--rootfs-only]
#                  [--mirror URL]
#
# --board pi3-4 (the default) is a Pi 3 or 4, arm64 or armhf; --board pi5 a Pi 5, arm64. --profile (default
# reference) is the built-in front-end profile the image's buses are made for: its `system` says how many chip
# selects SPI1 gets on a Pi 3 or 4 (appliance-image: one, appliance-image-spi1-3cs: three). DIR (default
# ./image-out) receives wheels/ (the Python packages), rootfs/ (the root file system) and, unless --rootfs-only,
# appliance-BOARD-ARCH.img. --rootfs-only stops at the root file system, for any architecture (amd64: this
# machine's, for the test); the image (Raspberry Pi partitions and firmware) is made for arm64 and armhf only.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
board=pi3-4 arch=arm64 profile=reference out=./image-out rootfs_only=no mirror=http://deb.debian.org/debian
while [ $# -gt 0 ]; do
    case $1 in
        --board) board=${2:?--board needs a value}; shift 2 ;;
        --arch) arch=${2:?--arch needs a value}; shift 2 ;;
        --profile) profile=${2:?--profile needs a name}; shift 2 ;;
        --out) out=${2:?--out needs a folder}; shift 2 ;;
        --rootfs-only) rootfs_only=yes; shift ;;
        --mirror) mirror=${2:?--mirror needs a URL}; shift 2 ;;
        *) echo "build-image.sh: unknown option '$1' (see the comment at the top of this script)" >&2; exit 2 ;;
    esac
done
# shellcheck source=board.sh
. "$here/board.sh"
board_build "$board" "$arch" || exit 2
if [ "$rootfs_only" = no ] && [ "$arch" = amd64 ]; then
    echo "build-image.sh: the SD-card image is for the Raspberry Pi (arm64 or armhf); use --rootfs-only for amd64" >&2
    exit 2
fi
# The profile's system, and so SPI1's chip selects.
profile_file=$here/../appliance/drivers/profiles/$profile.toml
[ -f "$profile_file" ] || { echo "build-image.sh: '$profile' is not a built-in profile (appliance/drivers/profiles/)" >&2
                            exit 2; }
system=$(python3 -c 'import sys, tomllib; print(tomllib.load(open(sys.argv[1], "rb")).get("system", "appliance-image"))' \
         "$profile_file")
case $board:$system in
    pi3-4:appliance-image) spi1_cs=1 ;;
    pi3-4:appliance-image-spi1-3cs) spi1_cs=3 ;;
    pi5:*) spi1_cs=0
           echo "build-image.sh: the Pi 5 image enables no SPI bus (Debian's kernel has no driver for RP1's SPI):" \
                "no built-in profile's front end runs on it (README.md in this folder)" >&2 ;;
    *) echo "build-image.sh: profile $profile runs on $system, which this recipe does not make for $board" >&2; exit 2 ;;
esac
# Every tool the build will need, checked before the long part starts: tool:Debian package.
tools="mmdebstrap:mmdebstrap python3:python3"
[ -z "$kernel" ] || tools="$tools dtc:device-tree-compiler fdtoverlay:device-tree-compiler fdtput:device-tree-compiler"
[ "$rootfs_only" = yes ] || tools="$tools sfdisk:fdisk mkfs.vfat:dosfstools mcopy:mtools mkfs.ext4:e2fsprogs"
for entry in $tools; do
    command -v "${entry%%:*}" >/dev/null ||
        { echo "build-image.sh: ${entry%%:*} is needed (apt-get install ${entry##*:})" >&2; exit 2; }
done
case $arch in arm64) qemu=qemu-aarch64 ;; armhf) qemu=qemu-arm ;; amd64) qemu=qemu-x86_64 ;; esac
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

echo "build-image.sh: the Python packages for $arch (Python $python)" >&2
rm -rf "$out/wheels"
"$here/wheelhouse.sh" "$arch" "$python" "$out/wheels"

# What a bed runs: systemd, Python for the appliance's virtual environment, nginx and openssl for the
# screen's TLS, overlayroot for the read-only root (its initramfs script needs busybox's grep), the file
# systems' checkers; on a Pi the Wi-Fi firmware, and then its kernel and boot firmware (hooks/raspi.sh), as
# Debian's own Pi images have them. On armhf numpy and scipy are Debian's (hooks/appliance.sh).
packages=systemd,systemd-sysv,systemd-timesyncd,udev,dbus,kmod,iproute2,libnss-myhostname,e2fsprogs,dosfstools
packages=$packages,python3,python3-venv,nginx,openssl,ca-certificates,overlayroot,busybox
hooks=(--customize-hook="\"$here/hooks/appliance.sh\" \"\$1\" \"$out/wheels\" $arch")
if [ -n "$kernel" ]; then
    packages=$packages,firmware-brcm80211
    hooks+=(--customize-hook="\"$here/hooks/raspi.sh\" \"\$1\" $board $arch $spi1_cs")
fi
hooks+=(--customize-hook="\"$here/hooks/image.sh\" \"\$1\"")
sources=("deb $mirror $suite main non-free-firmware" "deb $mirror $suite-updates main non-free-firmware"
         "deb http://security.debian.org/debian-security $suite-security main non-free-firmware")
[ -z "$kernel_suite" ] || [ "$kernel_suite" = "$suite" ] || sources+=("deb $mirror $kernel_suite main")

echo "build-image.sh: the root file system (Debian $suite, $arch) in $rootfs" >&2
mmdebstrap --mode=root --variant=minbase --arch="$arch" --components=main,non-free-firmware \
    --include="$packages" --setup-hook='mkdir -p "$1/boot/firmware"' "${hooks[@]}" \
    "$suite" "$rootfs" "${sources[@]}"

if [ "$rootfs_only" = no ]; then
    "$here/assemble-image.sh" "$rootfs" "$out/appliance-$board-$arch.img"
fi
