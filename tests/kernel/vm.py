"""A throw-away VM in which tests meet the Linux kernel's own bus simulators, gpio-sim and i2c-stub.

Why a VM: the simulators are kernel modules, so loading them takes root and a kernel that has them, and the
host's kernel is neither ours to change nor built with them (Debian bookworm's 6.1 and trixie's 6.12 lack
CONFIG_GPIO_SIM; Debian's 7.x kernels have it). So the tests boot Debian's kernel from ``SUITE`` under QEMU:

* the kernel and its modules come from Debian's archive through ``apt-get download`` with a package list
  of their own (the host's apt configuration is left alone), unpacked with ``dpkg-deb`` and cached per
  kernel version, so only the first run downloads (about 125 MB);
* the guest's root file system is the host's own, shared read-only over virtio-9p: the guest runs the same
  Python, virtual environment and checkout as the host, and nothing is installed twice;
* a small initramfs made for each boot (Debian's static busybox, the modules used, ``init.sh``) loads the
  modules, mounts the shares, runs a command and powers off. The command's output and exit status come
  back through a second, writable share.

KVM is used when it can run the guest, else QEMU's TCG emulation (slower, works anywhere). Needs
``qemu-system-x86`` and ``busybox-static`` (Debian packages; ``.ci/run`` installs them) and the network on
the first run. ``python tests/kernel/vm.py`` fetches and prepares the kernel ahead of a test run.
"""

from __future__ import annotations

import getpass
import lzma
import os
import platform
import re
import shlex
import shutil
import struct
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

SUITE = "forky"
"""Debian's suite the kernel comes from: the first whose amd64 kernel has gpio-sim."""
MIRROR = "http://deb.debian.org/debian"
KERNEL_PACKAGE = "linux-image-amd64"
MODULES = ("9p", "9pnet_virtio", "configfs", "gpio-sim", "i2c-dev", "i2c-stub")
"""Loaded in the guest, after the modules they depend on (found from each module's ``depends``)."""
INIT = Path(__file__).with_name("init.sh")
BUSYBOX = Path("/bin/busybox")
QEMU = "qemu-system-x86_64"
KVM_FAILURE = "KVM internal error"
"""What QEMU prints, then waits paused, when KVM cannot run an instruction of the guest."""
INSTALL_HINT = "apt-get install qemu-system-x86 busybox-static"


class VMUnavailable(RuntimeError):
    """Something the VM needs is missing; the message says what to install."""


@dataclass(frozen=True)
class Kernel:
    """An unpacked kernel: its version, its image and its tree of modules."""

    version: str
    vmlinuz: Path
    modules: Path


@dataclass(frozen=True)
class GuestRun:
    """What a command in the guest left: its exit status (None if it never finished), output and the console."""

    status: int | None
    output: str
    console: str
    accelerator: str


def cache_root() -> Path:
    """Where kernels are kept: ``$XDG_CACHE_HOME`` (else ~/.cache) / appliance / kernel-vm."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "appliance" / "kernel-vm"


def prepare(cache: Path | None = None) -> Kernel:
    """The newest kernel unpacked in ``cache``; the first time, download and unpack the suite's current one."""
    if platform.machine() != "x86_64":
        raise VMUnavailable(f"the test VM shares this host's programs, so it needs an x86-64 host, not "
                            f"{platform.machine()}")
    cache = cache or cache_root()
    ready = sorted(cache.glob("*/vmlinuz"), key=lambda path: path.stat().st_mtime)
    if ready:
        folder = ready[-1].parent
        return Kernel(folder.name, folder / "vmlinuz", _module_root(folder / "unpacked"))
    for tool in ("apt-get", "dpkg-deb"):
        if shutil.which(tool) is None:
            raise VMUnavailable(f"preparing the test kernel needs {tool} (a Debian or Ubuntu host)")
    apt = _PrivateApt(cache / "apt")
    image = apt.dependency(KERNEL_PACKAGE, "linux-image-")
    # From Debian's 7.x kernels the image package is empty and depends on linux-binary-* and linux-modules-*.
    packages = [image, *(name for name in apt.dependencies(image)
                         if name.startswith(("linux-binary-", "linux-modules-")))]
    folder = cache / image.removeprefix("linux-image-")
    unpacked = folder / "unpacked"
    shutil.rmtree(folder, ignore_errors=True)
    unpacked.mkdir(parents=True)
    for deb in apt.download(packages, folder):
        subprocess.run(["dpkg-deb", "-x", str(deb), str(unpacked)], check=True)
        deb.unlink()
    module_root = _module_root(unpacked)
    shutil.copyfile(_vmlinuz(unpacked, module_root), folder / "vmlinuz.part")
    (folder / "vmlinuz.part").rename(folder / "vmlinuz")    # last: a kernel with a vmlinuz is complete
    return Kernel(folder.name, folder / "vmlinuz", module_root)


class _PrivateApt:
    """apt-get and apt-cache on a package list of their own (``SUITE`` of Debian's archive) under ``folder``."""

    def __init__(self, folder: Path):
        (folder / "lists" / "partial").mkdir(parents=True, exist_ok=True)
        (folder / "cache" / "archives" / "partial").mkdir(parents=True, exist_ok=True)
        sources = folder / "sources.list"
        sources.write_text(f"deb {MIRROR} {SUITE} main\n")
        self.options = [f"-o{key}={value}" for key, value in (
            ("Dir::Etc::SourceList", sources), ("Dir::Etc::SourceParts", "/dev/null"),
            ("Dir::State::Lists", folder / "lists"), ("Dir::Cache", folder / "cache"),
            ("Dir::State::Status", "/dev/null"), ("APT::Sandbox::User", getpass.getuser()))]
        self._run("apt-get", "update", "-qq")

    def _run(self, tool: str, *args: str, cwd: Path | None = None) -> str:
        done = subprocess.run([tool, *self.options, *args], capture_output=True, text=True, cwd=cwd, check=False)
        if done.returncode:
            raise VMUnavailable(f"{tool} {' '.join(args)} failed for Debian {SUITE}: {done.stderr.strip()}")
        return done.stdout

    def dependencies(self, package: str) -> list[str]:
        out = self._run("apt-cache", "depends", package)
        return re.findall(r"^\s*Depends:\s*(\S+)", out, flags=re.MULTILINE)

    def dependency(self, package: str, prefix: str) -> str:
        """The one dependency of ``package`` whose name starts with ``prefix``."""
        names = [name for name in self.dependencies(package) if name.startswith(prefix)]
        if len(names) != 1:
            raise VMUnavailable(f"Debian {SUITE}'s {package} depends on {names or 'no'} {prefix}* packages")
        return names[0]

    def download(self, packages: list[str], folder: Path) -> list[Path]:
        self._run("apt-get", "download", "-qq", *packages, cwd=folder)
        return sorted(folder.glob("*.deb"))


def _module_root(unpacked: Path) -> Path:
    roots = [path for path in (unpacked / "lib" / "modules", unpacked / "usr" / "lib" / "modules") if path.is_dir()]
    versions = [version for root in roots for version in root.iterdir()]
    if len(versions) != 1:
        raise VMUnavailable(f"the kernel packages hold {len(versions)} module trees, expected one: {versions}")
    return versions[0]


def _vmlinuz(unpacked: Path, module_root: Path) -> Path:
    for path in (module_root / "vmlinuz", unpacked / "boot" / f"vmlinuz-{module_root.name}"):
        if path.is_file():
            return path
    raise VMUnavailable(f"no vmlinuz in the kernel packages of {module_root.name}")


def build_initramfs(module_root: Path, staging: Path, out: Path) -> None:
    """A newc cpio archive of ``staging`` (an empty folder, filled here): /init, busybox, and /modules with
    ``order`` listing them in loading order.

    Made for every boot (well under a second), so a change to ``init.sh`` or ``MODULES`` is never stale.
    """
    if not BUSYBOX.is_file():
        raise VMUnavailable(f"no {BUSYBOX}: {INSTALL_HINT}")
    if b"/ld-linux" in BUSYBOX.read_bytes()[:4096]:
        raise VMUnavailable(f"{BUSYBOX} is dynamically linked; the initramfs needs busybox-static: {INSTALL_HINT}")
    for folder in ("bin", "modules", "proc", "sys", "dev"):
        (staging / folder).mkdir()
    shutil.copy2(BUSYBOX, staging / "bin" / "busybox")
    shutil.copyfile(INIT, staging / "init")
    (staging / "init").chmod(0o755)
    files = {re.sub(r"\.ko(\.\w+)?$", "", path.name).replace("_", "-"): path
             for path in module_root.rglob("*.ko*")}
    order: list[str] = []

    def load(name: str) -> None:
        key = name.replace("_", "-")
        if key in order:
            return
        if key not in files:
            raise VMUnavailable(f"kernel {module_root.name} has no module {name} (built without it?)")
        code = _decompressed(files[key])
        for needed in filter(None, _modinfo(code).get("depends", "").split(",")):
            load(needed)
        (staging / "modules" / f"{key}.ko").write_bytes(code)
        order.append(key)

    for name in MODULES:
        load(name)
    (staging / "modules" / "order").write_text("\n".join(order) + "\n")
    listing = sorted(str(path.relative_to(staging)) for path in staging.rglob("*"))
    with out.open("wb") as archive:
        subprocess.run([str(BUSYBOX), "cpio", "-o", "-H", "newc"], input="\n".join(listing).encode(),
                       stdout=archive, stderr=subprocess.DEVNULL, cwd=staging, check=True)


def _decompressed(path: Path) -> bytes:
    data = path.read_bytes()
    return lzma.decompress(data) if path.suffix == ".xz" else data


def _modinfo(elf: bytes) -> dict[str, str]:
    """The ``key=value`` strings of a module's ``.modinfo`` section (64-bit little-endian ELF)."""
    section_offset, = struct.unpack_from("<Q", elf, 0x28)
    entry_size, count, names_index = struct.unpack_from("<HHH", elf, 0x3A)

    def section(index: int) -> tuple[int, int, int]:
        name, _, _, _, offset, size = struct.unpack_from("<IIQQQQ", elf, section_offset + index * entry_size)
        return name, offset, size

    _, names_offset, _ = section(names_index)
    for index in range(count):
        name, offset, size = section(index)
        if elf[names_offset + name:].startswith(b".modinfo\0"):
            fields = elf[offset:offset + size].split(b"\0")
            return dict(field.decode().partition("=")[::2] for field in fields if b"=" in field)
    return {}


def accelerators() -> list[str]:
    """QEMU's accelerators to try in turn: "kvm" first if /dev/kvm opens for reading and writing, then "tcg".

    An open /dev/kvm is not proof that KVM boots a stock kernel: a nested hypervisor without hardware
    virtualisation (such as PVM) stops on instructions its emulator lacks, so :func:`run` falls back on TCG.
    """
    try:
        os.close(os.open("/dev/kvm", os.O_RDWR))
    except OSError:
        return ["tcg"]
    return ["kvm", "tcg"]


def run(kernel: Kernel, command: str, out: Path, *, i2c_chips: list[int], timeout_s: float,
        memory_mb: int = 1024) -> GuestRun:
    """Boot ``kernel``, run ``command`` (a shell line) as root in the guest, and collect what it left in ``out``.

    The guest sees the host's files at the same paths (read-only) and ``out`` writable; i2c-stub answers at
    ``i2c_chips``. A guest that has not powered off after ``timeout_s`` is killed (``status`` None).
    """
    if shutil.which(QEMU) is None:
        raise VMUnavailable(f"no {QEMU}: {INSTALL_HINT}")
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    (out / "run.sh").write_text(f"{command}\n")
    with tempfile.TemporaryDirectory() as staging:
        build_initramfs(kernel.modules, Path(staging), out / "initramfs.cpio")
    chips = ",".join(f"0x{address:02x}" for address in i2c_chips)
    cmdline = f"console=ttyS0 panic=-1 quiet out={out} i2c_stub_chips={chips}"
    for accel in accelerators():
        for stale in ("status", "output.txt", "console.txt", "qemu.txt"):
            (out / stale).unlink(missing_ok=True)
        qemu = [QEMU, "-machine", "pc", "-accel", accel, "-cpu", "host" if accel == "kvm" else "max",
                "-smp", "1", "-m", str(memory_mb), "-nodefaults", "-no-user-config", "-display", "none",
                "-no-reboot", "-serial", f"file:{out / 'console.txt'}",
                "-kernel", str(kernel.vmlinuz), "-initrd", str(out / "initramfs.cpio"), "-append", cmdline,
                "-fsdev", "local,id=host,path=/,readonly=on,security_model=none,multidevs=remap",
                "-device", "virtio-9p-pci,fsdev=host,mount_tag=host",
                "-fsdev", f"local,id=out,path={out},security_model=none",
                "-device", "virtio-9p-pci,fsdev=out,mount_tag=out"]
        if _boot(qemu, out / "qemu.txt", timeout_s):
            break
    status = out / "status"
    return GuestRun(int(status.read_text()) if status.exists() else None, _text(out / "output.txt"),
                    _text(out / "console.txt"), accel)


def _boot(qemu: list[str], log: Path, timeout_s: float) -> bool:
    """Run QEMU until the guest powers off or ``timeout_s`` passes; False if KVM could not run the guest (an internal
    error, or QEMU stopping on KVM with an error of its own, such as an MSR the host's KVM refuses)."""
    with log.open("w") as messages:
        process = subprocess.Popen(qemu, stdout=messages, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + timeout_s
    kvm_failed = False
    try:
        while process.poll() is None and time.monotonic() < deadline and not kvm_failed:
            kvm_failed = KVM_FAILURE in _text(log)
            time.sleep(0.2)
    finally:
        stopped_by_us = process.poll() is None
        if stopped_by_us:
            process.kill()
        process.wait()
    if process.returncode and not stopped_by_us:
        if "kvm" in qemu:           # KVM refused the guest (an AMD host's KVM and "-cpu host" may): emulate instead
            return False
        raise VMUnavailable(f"{shlex.join(qemu[:5])} ... exited with {process.returncode}: {_text(log).strip()}")
    return not kvm_failed


def _text(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


if __name__ == "__main__":
    prepared = prepare()
    print(f"kernel {prepared.version}: {prepared.vmlinuz}, modules in {prepared.modules}")
