#!/usr/bin/env bash
# The Raspberry Pi device trees of the kernel a build installs (board.sh: BOARD on ARCH), fetched from Debian's
# archive into OUT without installing anything: the kernel package (and, where Debian splits it, the package of
# its device trees) unpacked in a scratch folder, its bcm2711/bcm2712/bcm2837 trees copied out. For checking the
# device-tree work of the recipe (device-trees.sh) against the very trees a bed boots, on any machine.
#
#   kernel-device-trees.sh BOARD ARCH OUT [MIRROR]
set -euo pipefail
usage="usage: kernel-device-trees.sh BOARD ARCH OUT [MIRROR]"
board=${1:?$usage}
arch=${2:?$usage}
out=${3:?$usage}
mirror=${4:-http://deb.debian.org/debian}
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=board.sh
. "$here/board.sh"
board_build "$board" "$arch"
[ -n "$kernel" ] || { echo "kernel-device-trees.sh: $board on $arch boots no Pi kernel" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/lists/partial" "$work/archives/partial" "$work/parts" "$out"
echo "deb [arch=$arch] $mirror $kernel_suite main" >"$work/sources.list"
: >"$work/status"
apt_options=(-o "Dir::State=$work" -o "Dir::State::Lists=$work/lists" -o "Dir::State::status=$work/status"
             -o "Dir::Cache=$work" -o "Dir::Cache::archives=$work/archives" -o "Dir::Etc::SourceList=$work/sources.list"
             -o "Dir::Etc::SourceParts=$work/parts" -o "Dir::Etc::Preferences=$work/preferences"
             -o "Dir::Etc::PreferencesParts=$work/parts" -o "APT::Architecture=$arch"
             -o "APT::Architectures::=$arch" -o "Acquire::Languages=none" -o "APT::Sandbox::User=root")
apt-get "${apt_options[@]}" update -qq
# The meta package names the versioned kernel; a kernel split into packages keeps its trees in linux-base-*.
version=$(apt-cache "${apt_options[@]}" depends "$kernel" | sed -n "s/^ *Depends: linux-image-\(.*\)/\1/p" | head -1)
[ -n "$version" ] || { echo "kernel-device-trees.sh: $kernel in $kernel_suite names no kernel" >&2; exit 1; }
packages=("linux-image-$version")
if apt-cache "${apt_options[@]}" show "linux-base-$version" >/dev/null 2>&1; then packages+=("linux-base-$version"); fi
(cd "$work/archives" && apt-get "${apt_options[@]}" download -qq "${packages[@]}" >/dev/null)
for deb in "$work/archives"/*.deb; do dpkg-deb -x "$deb" "$work/unpacked"; done
folder=$work/unpacked/$(device_tree_folder "$arch" "$version")
shopt -s nullglob
trees=("$folder"/bcm2711-rpi-*.dtb "$folder"/bcm2712-*rpi-*.dtb "$folder"/bcm2837-rpi-*.dtb)
[ ${#trees[@]} -gt 0 ] || { echo "kernel-device-trees.sh: linux-image-$version has no Pi device tree in" \
                                 "$(device_tree_folder "$arch" "$version")" >&2; exit 1; }
cp "${trees[@]}" "$out/"
echo "$version" >"$out/kernel-version"
