"""The image recipe (``image-build/``) run for this machine's architecture, and its root file system checked.

``build-image.sh --rootfs-only`` builds the root file system into a folder with mmdebstrap from Debian's
archive, through the same hooks as the Raspberry Pi image (only the Pi's firmware and kernel are left out),
so what is checked here is what a bed boots: the appliance runs from /opt/appliance, its units are enabled,
the service account, groups, folders and device rules exist, first-boot provisioning works inside it,
nginx accepts its configuration and the file system table makes the root read-only beside a data
partition. It needs root, mmdebstrap and the network (Debian's archive and PyPI); ``.ci/run`` installs
mmdebstrap. The build takes a few minutes, once for the module.

The Raspberry Pi builds (``--board pi3-4 --arch arm64|armhf``, ``--board pi5 --arch arm64``) need an ARM
emulator to run whole; what they do to the boot partition is checked here without one: the boot settings each
board's hook writes, and the device trees of the very kernel each build installs (fetched from Debian's archive
by ``kernel-device-trees.sh``) with the front end's buses written in by ``device-trees.sh``, held against the
image's systems in ``appliance/drivers/boards.py``.
"""

import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from appliance.drivers.boards import SYSTEMS
from appliance.drivers.profile import BUILTIN_PROFILES, board_profile

REPO = Path(__file__).resolve().parents[1]
RECIPE = REPO / "image-build"
UNITS = ("appliance-monitor.service", "appliance-screen.service", "appliance-provision.service", "nginx.service")
SETUP = """\
hostname = "ward3-bed12"

[admin]
name = "sister"
password = "correct horse battery"
"""


def host_architecture() -> str:
    return subprocess.run(["dpkg", "--print-architecture"], capture_output=True, text=True, check=True).stdout.strip()


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """The built root file system (a folder), removed after the module's tests."""
    if os.geteuid() != 0:
        pytest.fail("the image recipe needs root (mmdebstrap's root mode and chroot)")
    for tool in ("mmdebstrap", "chroot", "unshare", "systemctl"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} is needed to build the image's root file system (.ci/run installs it)")
    out = tmp_path_factory.mktemp("image")
    start = time.monotonic()
    result = subprocess.run([str(RECIPE / "build-image.sh"), "--arch", host_architecture(), "--rootfs-only",
                             "--out", str(out)], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-5000:]
    print(f"\nthe {host_architecture()} root file system was built in {time.monotonic() - start:.0f} s",
          file=sys.stderr)
    yield out / "rootfs"
    shutil.rmtree(out)


def in_root(root: Path, *command: str) -> subprocess.CompletedProcess:
    return subprocess.run(["chroot", str(root), *command], capture_output=True, text=True, check=False)


def table(path: Path) -> dict[str, list[str]]:
    """/etc/passwd or /etc/group: name -> fields."""
    return {line.split(":")[0]: line.split(":") for line in path.read_text().splitlines()}


def test_the_appliance_and_its_dependencies_run_from_opt_inside(root):
    result = in_root(root, "/opt/appliance/bin/python", "-c",
                     "import appliance, webui, numpy, scipy, flask, waitress, argon2, gpiod, spidev, smbus2; "
                     "import paho.mqtt; print(paho.mqtt.__version__)")
    assert result.returncode == 0, result.stderr
    assert int(result.stdout.split(".")[0]) >= 2                   # Debian's own paho-mqtt is 1.6
    result = in_root(root, "/opt/appliance/bin/appliance", "--help")
    assert result.returncode == 0 and "provision" in result.stdout, result.stderr
    assert (root / "opt/appliance/README.md").read_text() == (REPO / "README.md").read_text()
    assert not (root / "usr/bin/gcc").exists() and not (root / "tmp/wheels").exists()    # built, then removed


def test_the_bed_units_are_installed_and_enabled_and_the_ward_unit_is_not(root):
    for unit in UNITS[:2]:
        assert (root / "usr/lib/systemd/system" / unit).read_text() == (REPO / "systemd" / unit).read_text()
    for unit in UNITS:
        result = subprocess.run(["systemctl", f"--root={root}", "is-enabled", unit], capture_output=True, text=True,
                                check=False)
        assert result.stdout.strip() == "enabled", (unit, result.stdout, result.stderr)
        assert (root / "etc/systemd/system/multi-user.target.wants" / unit).is_symlink(), unit
    for unit in UNITS[:2] + ("nginx.service",):
        drop_in = (root / "etc/systemd/system" / f"{unit}.d/provisioning.conf").read_text()
        assert "Requires=appliance-provision.service" in drop_in, unit
    assert not list(root.glob("**/appliance-ward.service"))
    for unit in ("systemd-networkd.service", "systemd-resolved.service", "systemd-timesyncd.service"):
        assert subprocess.run(["systemctl", f"--root={root}", "is-enabled", unit], capture_output=True,
                              text=True, check=False).stdout.strip() == "enabled", unit


def test_the_units_verify_against_the_image_s_own_files(root):
    """systemd's checks with the image as the root: every ExecStart, user and drop-in as a bed has them."""
    result = subprocess.run(["systemd-analyze", "verify", "--man=no", f"--root={root}", *UNITS],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0 and result.stdout + result.stderr == "", result.stdout + result.stderr


def test_the_service_account_groups_folders_and_device_rules_exist(root):
    passwd, groups = table(root / "etc/passwd"), table(root / "etc/group")
    assert passwd["appliance"][5:] == ["/var/lib/appliance", "/usr/sbin/nologin"]
    for group in ("gpio", "spi", "i2c"):
        assert groups[group][3].split(",") == ["appliance"], group
    uid, gid = int(passwd["appliance"][2]), int(passwd["appliance"][3])
    for folder, mode, owner in (("var/lib/appliance", 0o750, (uid, gid)), ("var/cache/appliance", 0o750, (uid, gid)),
                                ("data/appliance", 0o750, (uid, gid)), ("data/etc", 0o755, (0, 0)),
                                ("etc/appliance", 0o755, (0, 0))):
        status = (root / folder).stat()
        assert (stat.S_IMODE(status.st_mode), (status.st_uid, status.st_gid)) == (mode, owner), folder
    assert (root / "etc/hostname").read_text() == "appliance\n"          # not the build machine's
    rules = root / "usr/lib/udev/rules.d/90-appliance.rules"
    assert rules.read_text() == (REPO / "systemd/90-appliance.rules").read_text()
    assert (root / "etc/modules-load.d/i2c-dev.conf").read_text().splitlines()[-1] == "i2c-dev"


def test_the_root_is_read_only_under_an_overlay_beside_the_data_partition(root):
    mounts = {fields[1]: fields for line in (root / "etc/fstab").read_text().splitlines()
              if line.strip() and not line.startswith("#") for fields in [line.split()]}
    assert mounts["/"][0] == "LABEL=APPROOT" and "ro" in mounts["/"][3].split(",")
    assert mounts["/data"][:3] == ["LABEL=APPDATA", "/data", "ext4"] and "rw" in mounts["/data"][3].split(",")
    assert mounts["/var/lib/appliance"][0] == "/data/appliance" and "bind" in mounts["/var/lib/appliance"][3]
    assert mounts["/etc/appliance"][0] == "/data/etc" and "bind" in mounts["/etc/appliance"][3]
    assert mounts["/boot/firmware"][2] == "vfat"
    assert 'overlayroot="tmpfs:swap=0,recurse=0"' in (root / "etc/overlayroot.local.conf").read_text()
    assert (root / "usr/share/initramfs-tools/scripts/init-bottom/overlayroot").exists()
    assert (root / "usr/bin/busybox").exists()                   # the overlayroot script's grep, in the initramfs
    assert "Storage=volatile" in (root / "etc/systemd/journald.conf.d/appliance.conf").read_text()
    for timer in ("apt-daily.timer", "apt-daily-upgrade.timer"):                 # nothing filling the overlay
        assert os.readlink(root / "etc/systemd/system" / timer) == "/dev/null", timer


def test_first_boot_provisioning_runs_inside_and_nginx_accepts_its_certificate(root):
    """As at a first boot: the data partition's folders bound over their mount points, in a private mount
    namespace that ends with the command, and the hostname left alone (it would be this machine's); then
    the monitor, as its service account, checks the configuration provisioning wrote."""
    setup = root / "boot/firmware/appliance-setup.toml"
    setup.write_text(SETUP)
    script = (f"mount --bind {root}/data/etc {root}/etc/appliance && "
              f"mount --bind {root}/data/appliance {root}/var/lib/appliance && "
              f"chroot {root} /opt/appliance/bin/appliance provision --no-hostname && chroot {root} nginx -t && "
              f"chroot --userspec=appliance:appliance {root} /opt/appliance/bin/appliance run "
              f"--config /etc/appliance/monitor.toml --check-config")
    result = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", script],
                            capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "created the screen's admin account 'sister'" in result.stderr
    assert "test is successful" in result.stderr
    assert "bed_id='ward3-bed12', " in result.stdout                # the monitor, as its account, reads its file
    uid = int(table(root / "etc/passwd")["appliance"][2])
    assert (root / "data/appliance/webui.db").stat().st_uid == uid
    assert stat.S_IMODE((root / "data/etc/tls/screen.key").stat().st_mode) == 0o600
    assert (root / "data/etc/hostname").read_text() == "ward3-bed12\n"
    assert "correct horse" not in setup.read_text()
    assert not list((root / "etc/appliance").iterdir())          # the mount point itself stays empty


PI_BUILDS = (("pi3-4", "arm64"), ("pi3-4", "armhf"), ("pi5", "arm64"))
SPI1_CHIP_SELECTS = {"appliance-image": 1, "appliance-image-spi1-3cs": 3}
"""The Pi 3 and 4 image's systems, by the chip selects device-trees.sh gives SPI1 (build-image.sh --profile)."""


@pytest.fixture(scope="module")
def kernel_trees(tmp_path_factory):
    """(board, arch) -> the folder of the Pi device trees of the kernel that build installs."""
    for tool in ("apt-get", "apt-cache", "dpkg-deb", "dtc", "fdtoverlay", "fdtget", "fdtput"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} is needed to check the image's device trees (.ci/run installs device-tree-compiler)")
    folders = {}
    for board, arch in PI_BUILDS:
        folder = tmp_path_factory.mktemp(f"trees-{board}-{arch}")
        result = subprocess.run([str(RECIPE / "kernel-device-trees.sh"), board, arch, str(folder)],
                                capture_output=True, text=True, check=False)
        assert result.returncode == 0, result.stderr[-3000:]
        folders[board, arch] = folder
    return folders


def fdtget(tree: Path, node: str, prop: str, kind: str = "u") -> list:
    result = subprocess.run(["fdtget", "-t", kind, str(tree), node, prop], capture_output=True, text=True, check=False)
    assert result.returncode == 0, f"{tree.name}: {node} {prop}: {result.stderr}"
    return [int(v) for v in result.stdout.split()] if kind == "u" else result.stdout.strip()


def subnodes(tree: Path, node: str) -> set[str]:
    return set(subprocess.run(["fdtget", "-l", str(tree), node], capture_output=True, text=True,
                              check=True).stdout.split())


@pytest.mark.parametrize("build", PI_BUILDS[:2], ids="-".join)
@pytest.mark.parametrize("system", sorted(SPI1_CHIP_SELECTS))
def test_the_pi3_4_trees_get_the_buses_the_image_s_system_claims(kernel_trees, tmp_path, build, system):
    facts = SYSTEMS[system]
    overlay = tmp_path / "appliance-buses.dtbo"
    subprocess.run(["dtc", "-@", "-q", "-I", "dts", "-O", "dtb", "-o", str(overlay),
                    str(RECIPE / "files/appliance-buses.dts")], check=True)
    stock = sorted(kernel_trees[build].glob("bcm2[78][13]*-rpi-*.dtb"))
    assert {t.name for t in stock} >= {"bcm2837-rpi-3-b.dtb", "bcm2837-rpi-3-b-plus.dtb", "bcm2711-rpi-4-b.dtb"}
    trees = []
    for tree in stock:
        trees.append(tmp_path / tree.name)
        shutil.copy(tree, trees[-1])
    result = subprocess.run([str(RECIPE / "device-trees.sh"), str(overlay), str(SPI1_CHIP_SELECTS[system]),
                             *map(str, trees)], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    for tree, original in zip(trees, stock):
        controller = fdtget(tree, "/soc/gpio@7e200000", "phandle")
        assert controller == fdtget(original, "/soc/gpio@7e200000", "phandle"), tree.name     # references intact
        spi0 = "/soc/spi@7e204000"
        assert fdtget(tree, spi0, "status", "s") == "okay" and subnodes(tree, spi0) == {"spidev@0", "spidev@1"}
        assert fdtget(tree, "/soc/gpio@7e200000/appliance-spi0-pins", "brcm,pins") == [7, 8, 9, 10, 11]
        spi1, chip_selects = "/soc/spi@7e215080", facts.spi_chip_selects[1]
        assert fdtget(tree, spi1, "status", "s") == "okay", tree.name
        assert fdtget(tree, spi1, "cs-gpios") == [v for pin in chip_selects for v in (*controller, pin, 1)]
        assert subnodes(tree, spi1) == {f"spidev@{k}" for k in range(len(chip_selects))}
        assert fdtget(tree, "/soc/gpio@7e200000/appliance-spi1-pins", "brcm,pins") == [19, 20, 21]
        assert fdtget(tree, "/soc/gpio@7e200000/appliance-spi1-pins", "brcm,function") == [3]     # ALT4
        assert fdtget(tree, "/soc/i2c@7e804000", "clock-frequency") == [facts.i2c_clock_hz[1]]
        assert fdtget(tree, "/soc/i2c@7e804000", "clock-frequency") != fdtget(original, "/soc/i2c@7e804000",
                                                                              "clock-frequency")
        assert fdtget(tree, "/aliases", "spi1", "s") == spi1 and fdtget(tree, "/aliases", "i2c1", "s") == \
            "/soc/i2c@7e804000"


def test_a_tree_the_overlay_does_not_fit_stops_the_bake(kernel_trees, tmp_path):
    overlay = tmp_path / "appliance-buses.dtbo"
    subprocess.run(["dtc", "-@", "-q", "-I", "dts", "-O", "dtb", "-o", str(overlay),
                    str(RECIPE / "files/appliance-buses.dts")], check=True)
    pi5 = tmp_path / "bcm2712-rpi-5-b.dtb"
    shutil.copy(kernel_trees["pi5", "arm64"] / pi5.name, pi5)
    result = subprocess.run([str(RECIPE / "device-trees.sh"), str(overlay), "1", str(pi5)], capture_output=True,
                            text=True, check=False)
    assert result.returncode == 1 and "the overlay does not fit" in result.stderr
    assert pi5.read_bytes() == (kernel_trees["pi5", "arm64"] / pi5.name).read_bytes()


def test_the_pi5_kernel_boots_the_pi5_but_has_no_spi_for_its_header(kernel_trees):
    """What appliance-image-pi5 claims: Debian's kernel has the Pi 5's tree, with RP1's I2C controllers but no
    SPI controller for the header, so the image enables none."""
    folder = kernel_trees["pi5", "arm64"]
    source = subprocess.run(["dtc", "-q", "-I", "dtb", "-O", "dts", str(folder / "bcm2712-rpi-5-b.dtb")],
                            capture_output=True, text=True, check=True).stdout
    assert '"raspberrypi,rp1-gpio"' in source and '"snps,designware-i2c"' in source
    assert "dw-apb-ssi" not in source
    assert not SYSTEMS["appliance-image-pi5"].spi_chip_selects
    assert "CONFIG_SPI_DESIGNWARE is not set" in SYSTEMS["appliance-image-pi5"].lacks


@pytest.mark.parametrize(("board", "console"), [("pi3-4", "ttyS1"), ("pi5", "ttyAMA10")])
def test_each_board_s_boot_settings(tmp_path, board, console):
    """What raspi-firmware's kernel hook turns into cmdline.txt and config.txt on the boot partition."""
    result = subprocess.run([str(RECIPE / "hooks/boot-config.sh"), str(tmp_path), board], capture_output=True,
                            text=True, check=False)
    assert result.returncode == 0, result.stderr
    settings = dict(line.split("=", 1) for line in (tmp_path / "etc/default/raspi-firmware").read_text().splitlines()
                    if line and not line.startswith("#"))
    assert settings == {"ROOTPART": "LABEL=APPROOT", "CONSOLES": f'"{console},115200 tty0"', "CMA": "0"}
    assert (tmp_path / "etc/default/raspi-extra-cmdline").read_text().split() == ["ro"]
    assert not (tmp_path / "etc/default/raspi-firmware-custom").exists()     # the buses are in the trees


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_the_recipe_makes_the_system_of_every_builtin_profile(name):
    system = board_profile({"profile": name}).system
    assert system in SPI1_CHIP_SELECTS
    assert len(SYSTEMS[system].spi_chip_selects[1]) == SPI1_CHIP_SELECTS[system]
    assert f"pi3-4:{system}) spi1_cs={SPI1_CHIP_SELECTS[system]}" in (RECIPE / "build-image.sh").read_text()
