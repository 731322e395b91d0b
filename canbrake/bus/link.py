"""What canbrake checks of a SocketCAN interface before a run: it is up, and a real CAN controller
runs at the scenario's ``bus.bitrate_bps`` and is not bus-off (a vcan has no bit rate). Read with
``ip -details -json link show`` (iproute2), sysfs as a fallback for up/down."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

from canbrake.errors import ScenarioError


def socketcan_link(channel: str) -> dict[str, Any]:
    """State of a SocketCAN interface from ``ip -details -json link show``: ``kind`` (vcan, can, ...),
    ``up`` (bool), ``bitrate_bps`` (int, or None where the kernel reports none, e.g. vcan) and
    ``state`` (the CAN controller state, e.g. ERROR-ACTIVE, BUS-OFF). Falls back to sysfs
    (operstate, type) without ``ip``. Raises OSError when the interface cannot be read."""
    info: dict[str, Any] = {"kind": None, "up": None, "bitrate_bps": None, "state": None}
    sys_dir = Path("/sys/class/net") / channel
    if shutil.which("ip"):
        r = subprocess.run(["ip", "-details", "-json", "link", "show", "dev", channel], capture_output=True,
                           text=True, timeout=10)
        if r.returncode == 0 and r.stdout.strip():
            link = json.loads(r.stdout)[0]
            li = link.get("linkinfo") or {}
            data = li.get("info_data") or {}
            info["kind"] = li.get("info_kind")
            info["up"] = "UP" in (link.get("flags") or []) and link.get("operstate") != "DOWN"
            info["bitrate_bps"] = (data.get("bittiming") or {}).get("bitrate")
            info["state"] = data.get("state")
            return info
    if not sys_dir.exists():
        raise OSError(f"no network interface {channel}")
    flags = int((sys_dir / "flags").read_text().strip(), 16)
    info["up"] = bool(flags & 1)
    return info


def check_socketcan_link(scn: Any, channel: str) -> None:
    """A real CAN interface must be up and run at ``bus.bitrate_bps``; a vcan has no bit rate."""
    try:
        link = socketcan_link(channel)
    except (OSError, ValueError, IndexError) as e:
        raise ScenarioError(f"--channel {channel}: cannot read the interface's state ({e}); check it with "
                            f"`ip -details link show {channel}`") from None
    if link["up"] is False:
        raise ScenarioError(f"--channel {channel}: the interface is down (bring it up: sudo ip link set {channel} "
                            f"up type can bitrate {scn.bus.bitrate_bps})")
    if link["kind"] == "can":
        rate = link["bitrate_bps"]
        if rate is None:
            raise ScenarioError(f"--channel {channel}: the kernel reports no bit rate for it; set it: sudo ip link "
                                f"set {channel} down && sudo ip link set {channel} up type can bitrate "
                                f"{scn.bus.bitrate_bps}")
        if int(rate) != int(scn.bus.bitrate_bps):
            raise ScenarioError(f"bus.bitrate_bps: {scn.bus.bitrate_bps} but {channel} runs at {rate} bit/s "
                                f"(set one to the other: --set bus.bitrate_bps={rate}, or sudo ip link set {channel} "
                                f"down && sudo ip link set {channel} up type can bitrate {scn.bus.bitrate_bps})")
        if str(link.get("state") or "").upper() == "BUS-OFF":
            raise ScenarioError(f"--channel {channel}: the controller is bus-off (check termination and wiring, then "
                                f"restart it: sudo ip link set {channel} type can restart)")
