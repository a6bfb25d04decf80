#!/usr/bin/env bash
# mmdebstrap customize hook: the appliance in the root file system ROOT, from the wheelhouse WHEELS
# (wheelhouse.sh): a virtual environment at /opt/appliance (where the systemd units run it from), the
# monitor's and the screen's units enabled, the service account, its folders and the device rules.
# The bed's own units only: the ward station's unit is for the station's machine, not an image for beds.
set -euo pipefail
root=${1:?usage: appliance.sh ROOT WHEELS}
wheels=${2:?usage: appliance.sh ROOT WHEELS}
repo=$(cd "$(dirname "$0")/../.." && pwd)
# A clean environment: the build machine's settings (PIP_*, PYTHON*) are not the image's.
in_root() { chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LC_ALL=C.UTF-8 \
    DEBIAN_FRONTEND=noninteractive "$@"; }

# spidev publishes no wheels: the wheelhouse holds its source, built here by the image's own compiler,
# which leaves the image afterwards.
build_tools="gcc libc6-dev python3-dev"
in_root apt-get install -y -qq --no-install-recommends $build_tools >/dev/null
mkdir -p "$root/tmp/wheels"
cp "$wheels"/* "$root/tmp/wheels/"
in_root python3 -m venv /opt/appliance
in_root /opt/appliance/bin/pip install -q --no-index --no-cache-dir --find-links /tmp/wheels 'appliance[hardware]'
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
