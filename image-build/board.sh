# Sourced by build-image.sh, hooks/raspi.sh and kernel-device-trees.sh: what each build (BOARD, ARCH) is made of.
#   suite          the Debian release of the root file system
#   python         its python3 (the appliance's wheels are fetched for it)
#   kernel         the kernel package, from kernel_suite (Debian's archive)
#   console        the serial console the kernel is told of (raspi-firmware's CONSOLES)
# pi3-4 arm64: bookworm's kernel has the Pi 3 and 4 trees. pi3-4 armhf: trixie, whose python3-numpy and
# python3-scipy are new enough for the appliance (PyPI has no armv7l wheels of them; bookworm's are 1.24 and
# 1.10). pi5 arm64: the first Debian kernel with the Pi 5's RP1 drivers is 7.3 in trixie-backports.
board_build() {
    case $1:$2 in
        pi3-4:arm64) suite=bookworm python=3.11 kernel=linux-image-arm64 kernel_suite=bookworm console=ttyS1 ;;
        pi3-4:armhf) suite=trixie python=3.13 kernel=linux-image-armmp-lpae kernel_suite=trixie console=ttyS1 ;;
        pi5:arm64) suite=trixie python=3.13 kernel=linux-image-arm64 kernel_suite=trixie-backports console=ttyAMA10 ;;
        pi3-4:amd64 | pi5:amd64) suite=bookworm python=3.11 kernel="" kernel_suite="" console="" ;;
        *) echo "no build for board '$1' on '$2' (pi3-4: arm64 or armhf; pi5: arm64; amd64: the root file system" \
                "alone)" >&2; return 2 ;;
    esac
}

# The folder of a kernel package's Raspberry Pi device trees, as raspi-firmware's hook looks for them.
device_tree_folder() {   # ARCH VERSION
    if [ "$1" = armhf ]; then echo "usr/lib/linux-image-$2"; else echo "usr/lib/linux-image-$2/broadcom"; fi
}
