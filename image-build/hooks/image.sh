#!/usr/bin/env bash
# mmdebstrap customize hook, after appliance.sh: what makes the root file system ROOT an appliance's
# rather than a computer's: a read-only root under a RAM overlay, the data partition's folders,
# first-boot provisioning, nginx as the screen's TLS front, and the network.
set -euo pipefail
root=${1:?usage: image.sh ROOT}
files=$(cd "$(dirname "$0")/../files" && pwd)
# A clean environment: the build machine's settings (PIP_*, PYTHON*) are not the image's.
in_root() { chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LC_ALL=C.UTF-8 \
    DEBIAN_FRONTEND=noninteractive "$@"; }

# Partitions and the read-only root (files/fstab explains the layout).
install -m 0644 "$files/fstab" "$root/etc/fstab"
install -m 0644 "$files/overlayroot.local.conf" "$root/etc/overlayroot.local.conf"
mkdir -p "$root/data" "$root/boot/firmware"
install -m 0644 "$files/appliance-image.tmpfiles" "$root/usr/lib/tmpfiles.d/appliance-image.conf"
in_root systemd-tmpfiles --create /usr/lib/tmpfiles.d/appliance-image.conf

# mmdebstrap copied the build machine's hostname in; a bed is "appliance" until provisioning names it.
echo appliance >"$root/etc/hostname"
install -m 0644 "$files/hosts" "$root/etc/hosts"

# Provisioning at first boot; the monitor, the screen and nginx wait for it.
install -m 0644 "$files/appliance-provision.service" "$root/usr/lib/systemd/system/"
for unit in appliance-monitor appliance-screen nginx; do
    install -D -m 0644 "$files/needs-provisioning.conf" "$root/etc/systemd/system/$unit.service.d/provisioning.conf"
done
in_root systemctl enable appliance-provision.service

# nginx: the screen over HTTPS only.
rm -f "$root/etc/nginx/sites-enabled/default"
install -m 0644 "$files/nginx-appliance.conf" "$root/etc/nginx/sites-available/appliance"
ln -sf ../sites-available/appliance "$root/etc/nginx/sites-enabled/appliance"
in_root systemctl enable nginx.service

# The journal in RAM (the root forgets it anyway) within a bound; no daily apt runs filling the overlay.
install -D -m 0644 "$files/journald.conf" "$root/etc/systemd/journald.conf.d/appliance.conf"
in_root systemctl mask apt-daily.timer apt-daily-upgrade.timer

# The front end's I2C bus as a device node.
install -m 0644 "$files/i2c-dev.conf" "$root/etc/modules-load.d/i2c-dev.conf"

# The network: DHCP on the wired interface, systemd's resolver and clock. systemd-resolved replaces
# /etc/resolv.conf by a link into /run, which ends name lookups inside this build: it comes last.
install -m 0644 "$files/wired.network" "$root/etc/systemd/network/20-wired.network"
in_root apt-get install -y -qq --no-install-recommends systemd-resolved >/dev/null
in_root systemctl enable systemd-networkd.service systemd-resolved.service systemd-timesyncd.service
in_root apt-get clean
