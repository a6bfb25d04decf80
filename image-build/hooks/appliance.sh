#!/usr/bin/env bash
# mmdebstrap customize hook: the appliance in the root file system ROOT, from the wheelhouse WHEELS
# (wheelhouse.sh) for ARCH: a virtual environment at /opt/appliance (where the systemd units run it from), the
# monitor's and the screen's units enabled, the service account, its folders and the device rules.
# The bed's own units only: the ward station's unit is for the station's machine, not an image for beds.
set -euo pipefail
usage="usage: appliance.sh ROOT WHEELS ARCH"
root=${1:?$usage}
wheels=${2:?$usage}
arch=${3:?$usage}
repo=$(cd "$(dirname "$0")/../.." && pwd)
# A clean environment: the build machine's settings (PIP_*, PYTHON*) are not the image's.
in_root() { chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LC_ALL=C.UTF-8 \
    DEBIAN_FRONTEND=noninteractive "$@"; }

# Packages published as source (spidev everywhere; on armhf every one PyPI has no armv7l wheel of) are built
# by the image's own compiler, which leaves the image afterwards. On armhf numpy and scipy are Debian's (PyPI
# has no armv7l wheels of them), seen from the virtual environment, and the sources build against Debian's
# setuptools and cffi.
build_tools="gcc libc6-dev python3-dev"
venv_args=() pip_args=()
if [ "$arch" = armhf ]; then
    in_root apt-get install -y -qq --no-install-recommends python3-numpy python3-scipy python3-cffi \
        python3-setuptools python3-setuptools-scm python3-wheel >/dev/null
    venv_args=(--system-site-packages) pip_args=(--no-build-isolation)
fi
in_root apt-get install -y -qq --no-install-recommends $build_tools >/dev/null
mkdir -p "$root/tmp/wheels"
cp "$wheels"/* "$root/tmp/wheels/"
in_root python3 -m venv "${venv_args[@]}" /opt/appliance
in_root /opt/appliance/bin/pip install -q --no-index --no-cache-dir "${pip_args[@]}" --find-links /tmp/wheels \
    'appliance[hardware]'
rm -rf "$root/tmp/wheels"
in_root apt-get purge -y -qq --autoremove $build_tools >/dev/null
install -m 0644 "$repo/README.md" "$root/opt/appliance/README.md"

install -m 0644 "$repo/systemd/appliance-monitor.service" "$repo/systemd/appliance-screen.service" \
    "$root/usr/lib/systemd/system/"
install -D -m 0644 "$repo/systemd/appliance.sysusers" "$root/usr/lib/sysusers.d/appliance.conf"
install -D -m 0644 "$repo/systemd/appliance.tmpfiles" "$root/usr/lib/tmpfiles.d/appliance.conf"
install -D -m 0644 "$repo/systemd/90-appliance.rules" "$root/usr/lib/udev/rules.d/90-appliance.rules"
in_root systemd-sysusers /usr/lib/sysusers.d/appliance.conf
in_root systemd-tmpfiles --create /usr/lib/tmpfiles.d/appliance.conf
in_root systemctl enable appliance-monitor.service appliance-screen.service
