#!/usr/bin/env bash
# The appliance and every Python package it needs for ARCH, as files in OUT for pip to install inside the
# image with no index: the appliance's wheel built here, its dependencies (pyproject.toml's, with the
# hardware extra a bed needs) as PyPI's manylinux wheels for the image's Python (Debian bookworm's 3.11).
# Debian's own python3-paho-mqtt (1.6) and python3-libgpiod (1.6) are older than the appliance needs.
set -euo pipefail
arch=${1:?usage: wheelhouse.sh ARCH OUT}
out=${2:?usage: wheelhouse.sh ARCH OUT}
repo=$(cd "$(dirname "$0")/.." && pwd)
case $arch in
    arm64) platform=manylinux2014_aarch64 ;;
    amd64) platform=manylinux2014_x86_64 ;;
    *) echo "wheelhouse.sh: no wheels known for architecture '$arch' (arm64 or amd64)" >&2; exit 2 ;;
esac
# Published as source only, so built inside the image (hooks/appliance.sh) with setuptools from here.
source_only="spidev"

mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# pip from a throw-away environment: Debian's python3 comes without it.
python3 -m venv "$work/venv"
pip=("$work/venv/bin/python" -m pip --disable-pip-version-check)
# Built from a copy: setuptools leaves a build/ folder in the tree it builds, and reuses it next time.
mkdir "$work/source"
cp -r "$repo/pyproject.toml" "$repo/README.md" "$repo/appliance" "$repo/webui" "$work/source/"
"${pip[@]}" wheel -q --no-deps -w "$out" "$work/source"
mapfile -t requirements < <(python3 - "$repo/pyproject.toml" <<'PY'
import sys, tomllib
project = tomllib.load(open(sys.argv[1], "rb"))["project"]
for requirement in project["dependencies"] + project["optional-dependencies"]["hardware"]:
    print(requirement)
PY
)
wheels=() sources=()
for requirement in "${requirements[@]}"; do
    name=${requirement%%[<>=!~ ;[]*}
    if [[ " $source_only " == *" $name "* ]]; then sources+=("$requirement"); else wheels+=("$requirement"); fi
done
"${pip[@]}" download -q -d "$out" --only-binary=:all: --platform "$platform" --python-version 3.11 \
    --implementation cp --abi cp311 "${wheels[@]}" setuptools
"${pip[@]}" download -q -d "$out" --no-binary=:all: --no-deps "${sources[@]}"
