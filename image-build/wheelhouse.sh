#!/usr/bin/env bash
# The appliance and every Python package it needs for ARCH and the image's Python (3.11 on bookworm, 3.13 on
# trixie), as files in OUT for pip to install inside the image with no index: the appliance's wheel built here,
# its dependencies (pyproject.toml's, with the hardware extra a bed needs) as PyPI's manylinux wheels for the
# image's Python. Debian's own python3-paho-mqtt (1.6) and bookworm's python3-libgpiod (1.6) are older than the
# appliance needs. PyPI has no armv7l wheels of numpy, scipy, gpiod or argon2-cffi-bindings: on armhf numpy and
# scipy (and cffi, the bindings' build dependency) are Debian's, installed by hooks/appliance.sh, and every
# other package is fetched on its own, as an armv7l or pure-Python wheel where PyPI has one, else as source
# that hooks/appliance.sh builds inside the image.
set -euo pipefail
usage="usage: wheelhouse.sh ARCH PYTHON OUT"
arch=${1:?$usage}
python=${2:?$usage}
out=${3:?$usage}
repo=$(cd "$(dirname "$0")/.." && pwd)
case $arch in
    arm64) platforms=(manylinux2014_aarch64) ;;
    amd64) platforms=(manylinux2014_x86_64) ;;
    armhf) platforms=(manylinux2014_armv7l manylinux_2_31_armv7l manylinux_2_36_armv7l) ;;
    *) echo "wheelhouse.sh: no wheels known for architecture '$arch' (arm64, armhf or amd64)" >&2; exit 2 ;;
esac
abi=cp${python/./}
platform_args=(--only-binary=:all: --python-version "$python" --implementation cp --abi "$abi" --abi abi3 --abi none)
for platform in "${platforms[@]}"; do platform_args+=(--platform "$platform"); done
# Published as source only, so built inside the image (hooks/appliance.sh) with setuptools from here.
source_only="spidev"
# Debian's on armhf (see above).
from_debian="numpy scipy cffi pycparser"

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
if [ "$arch" = armhf ]; then
    # Each package the requirements come to (as pip resolves them here), fetched on its own for the image.
    "${pip[@]}" download -q -d "$work/resolved" "${requirements[@]}"
    for file in "$work/resolved"/*; do
        name=$(basename "$file"); name=${name%%-[0-9]*}; version=$(basename "$file"); version=${version#"$name"-}
        version=${version%%-*}; version=${version%.tar.gz}; version=${version%.zip}
        canonical=$(tr 'A-Z_.' 'a-z--' <<<"$name")
        [[ " $from_debian " != *" $canonical "* ]] || continue
        "${pip[@]}" download -q -d "$out" --no-deps "${platform_args[@]}" "$name==$version" 2>/dev/null ||
            "${pip[@]}" download -q -d "$out" --no-deps --no-binary=:all: "$name==$version"
    done
    exit 0
fi
wheels=() sources=()
for requirement in "${requirements[@]}"; do
    name=${requirement%%[<>=!~ ;[]*}
    if [[ " $source_only " == *" $name "* ]]; then sources+=("$requirement"); else wheels+=("$requirement"); fi
done
"${pip[@]}" download -q -d "$out" "${platform_args[@]}" "${wheels[@]}" setuptools
"${pip[@]}" download -q -d "$out" --no-binary=:all: --no-deps "${sources[@]}"
