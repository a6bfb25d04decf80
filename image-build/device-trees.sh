#!/usr/bin/env bash
# The front end's buses baked into Raspberry Pi 3 and 4 device trees at build time: OVERLAY (appliance-buses.dtbo,
# compiled from files/appliance-buses.dts) applied to each TREE with fdtoverlay, then SPI1 cut to COUNT chip
# selects (1: GPIO 18; 3: GPIO 18, 17 and 16) and given its cs-gpios. Those must name the tree's own GPIO
# controller, which an overlay reaches only through the tree's symbols; the trees of Debian's arm64 kernel have
# none, and a label on the controller in the overlay makes fdtoverlay give it a new phandle, cutting every
# reference the tree already makes to it. So the controller's phandle is read from each tree and written here.
# A tree the overlay does not fit stops the build instead of a bed's boot.
#
#   device-trees.sh OVERLAY COUNT TREE...        each TREE is rewritten in place
set -euo pipefail
usage="usage: device-trees.sh OVERLAY COUNT TREE..."
overlay=${1:?$usage}
count=${2:?$usage}
shift 2
case $count in 1 | 3) ;; *) echo "device-trees.sh: SPI1 is given 1 or 3 chip selects, not '$count'" >&2; exit 2 ;; esac
[ $# -gt 0 ] || { echo "device-trees.sh: no device tree given ($usage)" >&2; exit 2; }
gpio_node=/soc/gpio@7e200000 spi1_node=/soc/spi@7e215080
chip_selects=(18 17 16)
for tree in "$@"; do
    baked=$tree.baked
    fdtoverlay -i "$tree" -o "$baked" "$overlay" ||
        { rm -f "$baked"; echo "device-trees.sh: the overlay does not fit $tree" >&2; exit 1; }
    controller=$(fdtget "$baked" "$gpio_node" phandle) ||
        { rm -f "$baked"; echo "device-trees.sh: $tree gives its GPIO controller no phandle" >&2; exit 1; }
    cs_gpios=()
    for pin in "${chip_selects[@]:0:count}"; do
        cs_gpios+=("$controller" "$pin" 1)                 # 1: GPIO_ACTIVE_LOW
    done
    fdtput -t u "$baked" "$spi1_node" cs-gpios "${cs_gpios[@]}"
    fdtput -t u "$baked" "$gpio_node/appliance-spi1-cs-pins" brcm,pins "${chip_selects[@]:0:count}"
    for ((unused = count; unused < ${#chip_selects[@]}; unused++)); do
        fdtput -r "$baked" "$spi1_node/spidev@$unused"
    done
    mv "$baked" "$tree"
done
