"""SocketCAN helpers: bring up a ``vcan`` interface and explain why a channel cannot be used.

Every problem surfaces as one :class:`VcanError` whose message says what is wrong and which
command fixes it, so the CLI can print it and exit 2 without a traceback:

- ``vcan_up(name)``: create and raise a virtual CAN interface (``canbrake vcan up NAME``).
- ``check_socketcan_channel(name)``: diagnose a channel before opening it.
- ``open_socketcan_bus(channel, **kw)``: ``can.Bus(interface="socketcan", ...)`` with python-can's
  ``OSError`` turned into the same clear message (``explain_socketcan_error`` does the mapping).

The system is probed through ``/sys`` (``SYSFS``) and the ``ip``/``modprobe`` commands (``_run``);
tests replace both.
"""

from __future__ import annotations

import errno
import os
import platform
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    import can

__all__ = [
    "VcanError",
    "vcan_up",
    "vcan_down",
    "check_socketcan_channel",
    "explain_socketcan_error",
    "open_socketcan_bus",
    "set_socket_rcvbuf",
    "socket_rcvbuf",
]

#: Root of sysfs; tests point this at a fake tree.
SYSFS = Path("/sys")

ARPHRD_CAN = 280  # /sys/class/net/NAME/type of every CAN interface (vcan, can0, vxcan ...)
IFF_UP = 0x1
CAP_NET_ADMIN = 12
_IFNAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,15}$")  # IFNAMSIZ - 1, no '/', ':' or spaces

#: One place that says where to go when the kernel has no CAN support at all.
NO_CAN_HINT = (
    "containers, WSL and sandboxes often run a kernel without CAN: use a Linux host or VM whose "
    "kernel has it (a throw-away QEMU/virtme-ng VM such as ../shared/tools/vcan-vm works; "
    "see docker/README.md), or run with `--bus memory`"
)


class VcanError(RuntimeError):
    """A SocketCAN/vcan problem, with a message that names the command that fixes it.

    ``kind`` is one of ``"no-kernel-support"``, ``"no-permission"``, ``"missing"``, ``"down"``,
    ``"not-can"``, ``"bad-name"``, ``"no-tool"``, ``"error"``.
    """

    def __init__(self, message: str, kind: str = "error") -> None:
        super().__init__(message)
        self.message = message
        self.kind = kind

    def __str__(self) -> str:
        return self.message


# --------------------------------------------------------------------------- system probes


def _run(argv: list[str]) -> subprocess.CompletedProcess[str]:
    """Run a system command, capturing its output (never raises for a non-zero exit)."""
    exe = shutil.which(argv[0], path=os.environ.get("PATH", "") + ":/usr/sbin:/sbin")
    if exe is None:
        return subprocess.CompletedProcess(argv, 127, "", f"{argv[0]}: command not found")
    return subprocess.run([exe, *argv[1:]], capture_output=True, text=True, check=False)


def _has_net_admin() -> bool:
    """True if this process may create and configure network interfaces."""
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        return True
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return bool(int(line.split()[1], 16) >> CAP_NET_ADMIN & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def _can_socket_error() -> OSError | None:
    """Try to open a raw CAN socket; return the error, or None if the kernel supports CAN_RAW."""
    if not hasattr(socket, "AF_CAN"):
        return OSError(errno.EAFNOSUPPORT, "this Python has no socket.AF_CAN")
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return exc
    sock.close()
    return None


def _is_linux() -> bool:
    return sys.platform.startswith("linux")


def _iface_dir(name: str) -> Path:
    return SYSFS / "class" / "net" / name


def _read_int(path: Path) -> int | None:
    try:
        return int(path.read_text().strip(), 0)
    except (OSError, ValueError):
        return None


def _iface_exists(name: str) -> bool:
    return _iface_dir(name).exists()


def _iface_is_can(name: str) -> bool:
    return _read_int(_iface_dir(name) / "type") == ARPHRD_CAN


def _iface_is_up(name: str) -> bool:
    flags = _read_int(_iface_dir(name) / "flags")
    return flags is not None and bool(flags & IFF_UP)


def _vcan_module_loaded() -> bool:
    return (SYSFS / "module" / "vcan").exists()


def _vcan_module_probe() -> tuple[bool, str]:
    """Whether ``modprobe vcan`` would find the module (dry run, needs no privileges), and why not."""
    if _vcan_module_loaded():
        return True, ""
    res = _run(["modprobe", "-n", "vcan"])
    return res.returncode == 0, (res.stderr or res.stdout).strip()


def _vcan_module_available() -> bool:
    return _vcan_module_probe()[0]


# --------------------------------------------------------------------------- messages


def _msg_no_module(detail: str = "") -> VcanError:
    why = f": {detail.strip()}" if detail.strip() else ""
    return VcanError(
        f"SocketCAN is not available: kernel {platform.release()} has no vcan module "
        f"(no /sys/module/vcan and `modprobe vcan` fails{why}). "
        "Fix: `sudo modprobe vcan` on a kernel that ships it (Ubuntu: "
        "`sudo apt-get install linux-modules-extra-$(uname -r)` first); "
        f"{NO_CAN_HINT}.",
        "no-kernel-support",
    )


def _msg_no_can_raw(exc: OSError) -> VcanError:
    return VcanError(
        f"SocketCAN is not available: kernel {platform.release()} refuses CAN sockets "
        f"({exc.strerror or exc}). Fix: `sudo modprobe can_raw` (and `sudo modprobe vcan`); "
        f"{NO_CAN_HINT}.",
        "no-kernel-support",
    )


def _msg_no_permission(name: str) -> VcanError:
    return VcanError(
        f"creating or raising {name} needs root or CAP_NET_ADMIN (running as uid {os.getuid()} "
        f"without it). Fix: `sudo canbrake vcan up {name}` or "
        f"`sudo ip link add dev {name} type vcan && sudo ip link set up {name}`.",
        "no-permission",
    )


def _msg_missing(name: str) -> VcanError:
    hw = (
        ""
        if name.startswith("vcan")
        else " (if it is a CAN adapter, check that it is plugged in and its driver loaded: "
        "`ip -details link show`)"
    )
    return VcanError(
        f"CAN interface {name} does not exist{hw}. Fix: `canbrake vcan up {name}` "
        f"(as root, e.g. `sudo canbrake vcan up {name}`).",
        "missing",
    )


def _msg_down(name: str) -> VcanError:
    if name.startswith("vcan"):
        fix = f"`sudo ip link set up {name}` (or `sudo canbrake vcan up {name}`)"
    else:
        fix = f"`sudo ip link set {name} up type can bitrate 500000` (use your bus's bit rate)"
    return VcanError(f"CAN interface {name} is down. Fix: {fix}.", "down")


def _msg_not_can(name: str) -> VcanError:
    kind = _read_int(_iface_dir(name) / "type")
    return VcanError(
        f"{name} is not a CAN interface (link type {kind}, CAN is {ARPHRD_CAN}). Fix: pick a CAN "
        "channel, e.g. `--channel vcan0` (`ip -details link show type vcan` lists them; "
        "`canbrake vcan up vcan0` makes one).",
        "not-can",
    )


def _check_name(name: str) -> None:
    if not _IFNAME_RE.match(name or ""):
        raise VcanError(
            f"invalid interface name {name!r}: use 1-15 letters, digits, '_', '-' or '.', "
            "e.g. `canbrake vcan up vcan0`.",
            "bad-name",
        )


def _check_linux() -> None:
    if not _is_linux():
        raise VcanError(
            f"SocketCAN needs Linux (this is {sys.platform}). Fix: run on a Linux host or VM "
            "with `canbrake vcan up vcan0`, or use `--bus memory`.",
            "no-kernel-support",
        )


# --------------------------------------------------------------------------- public API


def vcan_up(name: str = "vcan0") -> str:
    """Create (if needed) and raise the virtual CAN interface ``name``.

    Loads the ``vcan`` module if it is missing. Idempotent: an interface that is already up is
    left alone. Returns a one-line description of what was done; raises :class:`VcanError`.
    """
    _check_name(name)
    _check_linux()
    if _iface_exists(name):
        if not _iface_is_can(name):
            raise _msg_not_can(name)
        if _iface_is_up(name):
            return f"{name} is already up"
        if not _has_net_admin():
            raise _msg_no_permission(name)
        _ip_set_up(name)
        return f"{name} raised"

    privileged = _has_net_admin()
    if not _vcan_module_loaded():
        if not privileged:
            available, why = _vcan_module_probe()
            if not available:
                raise _msg_no_module(why)
            raise _msg_no_permission(name)
        res = _run(["modprobe", "vcan"])
        if res.returncode != 0 and not _vcan_module_loaded():
            raise _msg_no_module(res.stderr or res.stdout)
    if not privileged:
        raise _msg_no_permission(name)

    res = _run(["ip", "link", "add", "dev", name, "type", "vcan"])
    if res.returncode != 0 and not _iface_exists(name):
        raise _explain_ip_failure(name, res)
    _ip_set_up(name)
    if _can_socket_error() is not None:  # the interface is there, CAN_RAW may still be missing
        _run(["modprobe", "can_raw"])
        err = _can_socket_error()
        if err is not None:
            raise _msg_no_can_raw(err)
    return f"{name} created and up"


def vcan_down(name: str) -> None:
    """Delete the interface ``name`` (``ip link del``); missing interfaces are ignored."""
    _check_name(name)
    if not _iface_exists(name):
        return
    if not _has_net_admin():
        raise _msg_no_permission(name)
    res = _run(["ip", "link", "del", "dev", name])
    if res.returncode != 0 and _iface_exists(name):
        raise _explain_ip_failure(name, res)


def _ip_set_up(name: str) -> None:
    res = _run(["ip", "link", "set", "up", name])
    if res.returncode != 0 or not _iface_is_up(name):
        raise _explain_ip_failure(name, res)


def _explain_ip_failure(name: str, res: subprocess.CompletedProcess[str]) -> VcanError:
    """Turn an ``ip`` command's failure into one clear message."""
    out = (res.stderr or "") + (res.stdout or "")
    low = out.lower()
    if res.returncode == 127:
        return VcanError(
            "the `ip` command was not found. Fix: install iproute2 "
            f"(`sudo apt-get install iproute2`), then `sudo canbrake vcan up {name}`.",
            "no-tool",
        )
    if "unknown device type" in low or "not supported" in low:
        return _msg_no_module(out)
    if "operation not permitted" in low or "permission denied" in low:
        return _msg_no_permission(name)
    if "cannot find device" in low:
        return _msg_missing(name)
    cmd = " ".join(str(a) for a in res.args)
    return VcanError(
        f"`{cmd}` failed: {out.strip() or f'exit {res.returncode}'}. "
        f"Fix: check `ip -details link show {name}`, then `sudo canbrake vcan up {name}`.",
        "error",
    )


def check_socketcan_channel(name: str) -> None:
    """Raise :class:`VcanError` unless ``name`` is an existing, up CAN interface usable here."""
    _check_name(name)
    _check_linux()
    err = _can_socket_error()
    if err is not None:
        available, why = _vcan_module_probe()
        if not available:
            raise _msg_no_module(why)
        raise _msg_no_can_raw(err)
    if not _iface_exists(name):
        if name.startswith("vcan"):
            available, why = _vcan_module_probe()
            if not available:
                raise _msg_no_module(why)
        raise _msg_missing(name)
    if not _iface_is_can(name):
        raise _msg_not_can(name)
    if not _iface_is_up(name):
        raise _msg_down(name)


def _errno_of(exc: BaseException) -> int | None:
    """The errno of ``exc`` or of the OSError it wraps (python-can wraps some)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        code = getattr(cur, "errno", None)
        if isinstance(code, int):
            return code
        code = getattr(cur, "error_code", None)  # can.CanError keeps the OS errno here
        if isinstance(code, int) and code > 0:
            return code
        cur = cur.__cause__ or cur.__context__
    return None


def explain_socketcan_error(exc: BaseException, channel: str) -> VcanError:
    """Map an error from opening/using ``socketcan`` channel ``channel`` to a clear VcanError."""
    if isinstance(exc, VcanError):
        return exc
    code = _errno_of(exc)
    if code in (errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT):
        try:
            check_socketcan_channel(channel)
        except VcanError as err:
            return err
        return _msg_no_can_raw(OSError(code, os.strerror(code)))
    if code == errno.ENODEV:
        return _msg_missing(channel)
    if code == errno.ENETDOWN:
        return _msg_down(channel)
    if code in (errno.EPERM, errno.EACCES):
        return VcanError(
            f"not allowed to open a CAN socket on {channel} ({exc}). Fix: run as a user allowed "
            f"to (e.g. `sudo`), or in Docker add `network_mode: host` (see docker/README.md).",
            "no-permission",
        )
    try:
        check_socketcan_channel(channel)
    except VcanError as err:
        return err
    return VcanError(
        f"could not use SocketCAN channel {channel}: {exc}. "
        f"Fix: check `ip -details -statistics link show {channel}`.",
        "error",
    )


def open_socketcan_bus(
    channel: str = "vcan0", *, rcvbuf_bytes: int | None = None, **kwargs: Any
) -> can.BusABC:
    """Open ``can.Bus(interface="socketcan", channel=channel, **kwargs)``.

    Checks the channel first and turns python-can's ``OSError``/``CanError`` into
    :class:`VcanError` with a message that names the fix.

    ``rcvbuf_bytes``: enlarge the socket's receive queue. The kernel silently drops frames
    for a reader that falls behind once its queue (``net.core.rmem_default``, about 200 KB, a few
    hundred frames) is full; a recorder that must see every frame wants several MB. Uses
    ``SO_RCVBUFFORCE`` when allowed (CAP_NET_ADMIN), else ``SO_RCVBUF`` (capped at
    ``net.core.rmem_max``). :func:`socket_rcvbuf` reports what the kernel granted.
    """
    import can

    check_socketcan_channel(channel)
    try:
        bus = can.Bus(interface="socketcan", channel=channel, **kwargs)
    except (OSError, can.CanError) as exc:
        raise explain_socketcan_error(exc, channel) from exc
    if rcvbuf_bytes:
        sock = getattr(bus, "socket", None)
        if isinstance(sock, socket.socket):
            set_socket_rcvbuf(sock, rcvbuf_bytes)
    return bus


def set_socket_rcvbuf(sock: socket.socket, nbytes: int) -> int:
    """Ask for a receive queue of ``nbytes`` (forced past rmem_max if privileged); return the grant."""
    force = getattr(socket, "SO_RCVBUFFORCE", 33)
    try:
        sock.setsockopt(socket.SOL_SOCKET, force, nbytes)
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, nbytes)
    return socket_rcvbuf(sock)


def socket_rcvbuf(sock: socket.socket) -> int:
    """The socket's receive buffer size as the kernel reports it (twice the usable payload)."""
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
