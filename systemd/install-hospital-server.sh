#!/usr/bin/env bash
# Install a hospital server on Debian from the hospital description: its engine node(s) and, where PostgreSQL
# runs, the history writer, as systemd units of the account appliance-hospital. Run as root from a checkout:
#
#   systemd/install-hospital-server.sh --description hospital.toml [--node NAME]... [--no-history]
#                                     [--notifier NAME]... [--prefix DIR] [--root DIR]
#
# --node (repeat) names the description's nodes this server runs (default: all of them, a one-server trial);
# --no-history leaves out PostgreSQL and the writer; --notifier (repeat) names the description's notification
# services this server runs (default: none). --prefix (default /opt/appliance) is the appliance's
# environment, made and filled from this checkout with the `hospital` extra if it has no pip yet; --root (default
# /) is where the files go. It can be run again: passwords are kept, the database and role are made once.
# With [tls] in the description, its folder must hold the CA's certificate and each named node's certificate and
# key (appliance hospital certs makes them): they are copied to /etc/appliance/hospital/tls, owned by the account.
# Then, once every server runs its node: appliance hospital streams --description ... --secrets
# /etc/appliance/hospital/secrets, which makes the wards' streams.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
description="" nodes=() notifiers=() history=yes prefix=/opt/appliance root=/
while [ $# -gt 0 ]; do
    case $1 in
        --description) description=${2:?--description needs a file}; shift 2 ;;
        --node) nodes+=("--node" "${2:?--node needs a name}"); shift 2 ;;
        --no-history) history=no; shift ;;
        --notifier) notifiers+=("--notifier" "${2:?--notifier needs a name}"); shift 2 ;;
        --prefix) prefix=${2:?--prefix needs a folder}; shift 2 ;;
        --root) root=${2:?--root needs a folder}; shift 2 ;;
        *) echo "install-hospital-server.sh: unknown option '$1' (see the comment at the top of this script)" >&2
           exit 2 ;;
    esac
done
[ -n "$description" ] || { echo "install-hospital-server.sh: --description is required" >&2; exit 2; }
[ -f "$description" ] || { echo "install-hospital-server.sh: $description is not a file" >&2; exit 2; }

packages=(python3-venv)
[ "$history" = no ] || packages+=(postgresql)
apt-get install -y -qq "${packages[@]}"
[ -x "$prefix/bin/pip" ] || python3 -m venv "$prefix"
"$prefix/bin/pip" install -q "$repo[hospital]"

# The account, then the units (templates: one node instance per node this server runs).
install -D -m 0644 "$repo/systemd/appliance-hospital.sysusers" "$root/usr/lib/sysusers.d/appliance-hospital.conf"
systemd-sysusers --root="$root" "$root/usr/lib/sysusers.d/appliance-hospital.conf"
install -D -m 0644 -t "$root/usr/lib/systemd/system" "$repo/systemd/appliance-hospital-node@.service" \
    "$repo/systemd/appliance-hospital-history.service" "$repo/systemd/appliance-hospital-overview.service" \
    "$repo/systemd/appliance-hospital-notify@.service"

install_args=(--description "$description" --root "$root" "${nodes[@]}" "${notifiers[@]}")
[ "$history" = yes ] || install_args+=(--no-history)
units=$("$prefix/bin/appliance" hospital install "${install_args[@]}")
chown -R appliance-hospital:appliance-hospital "$root/etc/appliance/hospital"

if [ "$history" = yes ]; then
    runuser -u postgres -- psql -X -q -v ON_ERROR_STOP=1 -f - < "$root/etc/appliance/hospital/history-setup.sql"
fi
systemctl daemon-reload
# shellcheck disable=SC2086  # one unit a word
systemctl enable --now $units
echo "installed and started: $(echo $units)"
