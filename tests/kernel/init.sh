#!/bin/busybox sh
# PID 1 of the test VM (vm.py packs it into the initramfs as /init, beside busybox and the modules).
#
# It loads the modules listed in /modules/order, mounts the host's root file system (shared read-only over
# virtio-9p, tag "host") at /host and the output folder (writable, tag "out") at the path it has on the host,
# runs that folder's run.sh chrooted into the host's root with the guest's own /proc, /sys and /dev, writes
# its exit status to the folder's "status" file, and powers off. Scratch space is a tmpfs at /dev/shm
# (TMPDIR and HOME), not over /tmp: the host's /tmp stays visible, since the checkout may be there. The kernel hands the unknown
# parameters of its command line to init as variables: "out" (the output folder's host path) and
# "i2c_stub_chips" (the addresses i2c-stub answers at).
/bin/busybox --install -s /bin
export PATH=/bin

mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev

fail() {
    echo "guest init: $*"
    poweroff -f
}

for module in $(cat /modules/order); do
    case $module in
        i2c-stub) insmod "/modules/$module.ko" "chip_addr=$i2c_stub_chips" ;;
        *) insmod "/modules/$module.ko" ;;
    esac || fail "loading $module failed"
done

mkdir -p /host
mount -t 9p -o ro,trans=virtio,version=9p2000.L,msize=512000,cache=loose host /host || fail "no host share"
mount -t proc proc /host/proc
mount -t sysfs sysfs /host/sys
mount -t configfs configfs /host/sys/kernel/config
mount -t devtmpfs devtmpfs /host/dev
mkdir -p /host/dev/shm
mount -t tmpfs -o mode=1777 tmpfs /host/dev/shm
export HOME=/dev/shm TMPDIR=/dev/shm
mkdir -p "/host$out"
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 out "/host$out" || fail "no output share"

chroot /host /bin/sh "$out/run.sh" > "/host$out/output.txt" 2>&1
echo $? > "/host$out/status"
umount "/host$out"
poweroff -f
