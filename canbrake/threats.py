"""The EN 50159 threat matrix as runnable experiments: one injector per threat, each run with and
without authentication (``security:``) against the same clean run, and what the defences did.

Set-up: Chen case 1 (six cars, ideal actuator, 1 ms period) for :data:`DURATION_S`, the in-process
engine, fail-safe on (``safety.command_timeout_s`` = :data:`TIMEOUT_S`, latched). From
:data:`ATTACK_S` on, the injector acts on car 3's brake commands (BRAKE_CMD_C3) or on the
simulation-control frames, through the impairment layer (the sender's own send path) or a rogue
node on the bus (``babble`` with a phantom sender, hosted by the plant: its frames arrive at the
start of each period, before that period's genuine command).

Used by the tests (``tests/test_threats.py``: one test per threat and security setting) and by
``canbrake report safety``, which writes the measured table into ``docs/safety.md``.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

ATTACK_S = 0.05
TIMEOUT_S = 0.02
DURATION_S = 0.15
CAR = 3
CMD_ID = 0x080 + CAR          # BRAKE_CMD_C3
STATE_ID = 0x140 + CAR        # STATE_C3 (to the other five ECUs)
STATE_AUTH_ID = 0x180 + CAR   # STATE_AUTH_C3, its authenticator in secured runs
UNKNOWN_CMD_ID = 0x080 + 63   # BRAKE_CMD of a car 63 the six-car train does not have
SYNC_ID = 0x010
REPLAY_FROM_TICK = 10         # the logged frame the rogue replays


@dataclass(frozen=True)
class Expect:
    """What the test asserts for one security setting."""

    reasons: tuple[str, ...] = ()   # rejection reasons that must be counted (> 0)
    failsafe: bool = False          # car 3's brake unit must enter fail-safe at ATTACK_S + TIMEOUT_S + T
    unchanged: bool = False         # signals.csv byte-identical to the clean run's
    undetected: bool = False        # the attack changes braking and nothing is rejected for it


@dataclass(frozen=True)
class Threat:
    key: str
    threat: str                     # EN 50159 name
    injector: str
    defence: str
    impairments: Callable[["Context"], list[dict[str, Any]]]
    expect: dict[bool, Expect]      # by "authenticated"


@dataclass
class Context:
    """What an injector may use: the clean run of the same security setting and its database."""

    clean_dir: Path
    secured: bool
    codec: Any


def _logged(ctx: Context, aid: int = CMD_ID) -> str:
    """Hex payload of car 3's frame ``aid`` of tick REPLAY_FROM_TICK as recorded in the clean frames.log."""
    import can

    frames = [m for m in can.LogReader(str(ctx.clean_dir / "frames.log")) if m.arbitration_id == aid]
    return bytes(frames[REPLAY_FROM_TICK].data).hex()


def _logged_command(ctx: Context) -> str:
    return _logged(ctx, CMD_ID)


def _state_replay(ctx: Context) -> list[dict[str, Any]]:
    """The logged STATE_C3 of tick REPLAY_FROM_TICK and, secured, its logged authenticator."""
    out = [_rogue(STATE_ID, _logged(ctx, STATE_ID))]
    if ctx.secured:
        out.append(_rogue(STATE_AUTH_ID, _logged(ctx, STATE_AUTH_ID)))
    return out


def _forged_state(ctx: Context) -> str:
    """Car 3 at standstill at position 0, valid E2E CRC, counter 0 (no authenticator: the key is secret)."""
    return ctx.codec["STATE_C3"].encode({"Speed": 0.0, "Position": 0.0}, counter=0).hex()


def _forged_command(ctx: Context) -> str:
    """A 0 N command for car 3 with a valid E2E CRC and counter 0 (and, secured, a guessed MAC of 0)."""
    return ctx.codec["BRAKE_CMD_C3"].encode({"Status": 0, "BrakeForce": 0.0}, counter=0).hex()


def _forged_end(ctx: Context) -> str:
    n = ctx.codec["SYNC"].length
    return (0xFFFFFFFF).to_bytes(4, "little").hex() + "00" * (n - 4)


def _rogue(aid: int, data_hex: str) -> dict[str, Any]:
    return {"type": "babble", "sender": "rogue", "arbitration_id": aid, "rate_hz": 1000.0,
            "dlc": len(data_hex) // 2, "data_hex": data_hex, "start_s": ATTACK_S}


_ON_CMD = {"ids": [CMD_ID], "start_s": ATTACK_S}

THREATS: list[Threat] = [
    Threat("replay_logged", "repetition",
           f"rogue node re-sends car {CAR}'s logged command of tick {REPLAY_FROM_TICK} every period",
           "alive counter (newer than the last accepted, 7-period window); SecOC freshness",
           lambda ctx: [_rogue(CMD_ID, _logged_command(ctx))],
           {False: Expect(reasons=("counter",), undetected=True), True: Expect(reasons=("counter", "freshness"), unchanged=True)}),
    Threat("replay_15", "repetition",
           "each command repeated verbatim 14.9 periods later (impairment `duplicate`): its counter aliases",
           "alive counter; SecOC freshness",
           lambda ctx: [{"type": "duplicate", "probability": 1.0, "gap_s": 0.0149, **_ON_CMD}],
           {False: Expect(reasons=("counter",), undetected=True), True: Expect(reasons=("freshness",), unchanged=True)}),
    Threat("deletion", "deletion", "every command lost (impairment `loss`)",
           "time-out: fail-safe brake after safety.command_timeout_s",
           lambda ctx: [{"type": "loss", "probability": 1.0, **_ON_CMD}],
           {False: Expect(failsafe=True), True: Expect(failsafe=True)}),
    Threat("insertion", "insertion",
           "rogue node sends commands for a car the train does not have (BRAKE_CMD_C63, 0x0BF)",
           "source identifier (id plan): counted as unknown sender, ignored",
           lambda ctx: [_rogue(UNKNOWN_CMD_ID, "00" * ctx.codec["BRAKE_CMD_C3"].length)],
           {False: Expect(reasons=("unknown_sender",), unchanged=True), True: Expect(reasons=("unknown_sender",), unchanged=True)}),
    Threat("forged_end", "insertion",
           "rogue node sends SYNC with tick 0xFFFFFFFF (end of run) every period",
           "SYNC sequence check (only the next tick, only after the tick is complete); SecOC on SYNC",
           lambda ctx: [_rogue(SYNC_ID, _forged_end(ctx))],
           {False: Expect(reasons=("sync",), unchanged=True), True: Expect(reasons=("sync",), unchanged=True)}),
    Threat("flood", "insertion (flooding)",
           "rogue node floods identifier 0x001 (highest priority) at 100 kHz",
           "acceptance filters keep it out of the nodes (in-memory bus: it may not overwrite a frame a lockstep "
           "node accepts, tests/test_flood.py); the recorder names the identifier",
           lambda ctx: [{"type": "babble", "sender": "rogue", "arbitration_id": 1, "rate_hz": 100_000.0, "dlc": 8,
                         "start_s": ATTACK_S}],
           {False: Expect(unchanged=True), True: Expect(unchanged=True)}),
    Threat("resequencing", "resequencing",
           "half the commands held back 1-3 periods (impairment `reorder`)",
           "alive counter: an older frame after a newer one is dropped",
           lambda ctx: [{"type": "reorder", "probability": 0.5, "hold_min_s": 0.001, "hold_max_s": 0.003, **_ON_CMD}],
           {False: Expect(reasons=("counter",)), True: Expect(reasons=("counter",))}),
    Threat("corruption", "corruption", "one bit flipped in every command (impairment `corrupt`)",
           "E2E CRC-8; then time-out",
           lambda ctx: [{"type": "corrupt", "probability": 1.0, "n_bits": 1, **_ON_CMD}],
           {False: Expect(reasons=("crc",), failsafe=True), True: Expect(reasons=("crc",), failsafe=True)}),
    Threat("delay_25", "delay", "every command delayed by 25 periods (impairment `delay`)",
           "alive counter window (7 periods), then time-out",
           lambda ctx: [{"type": "delay", "delay_s": 0.025, **_ON_CMD}],
           {False: Expect(reasons=("counter",), failsafe=True), True: Expect(reasons=("counter",), failsafe=True)}),
    Threat("delay_15", "delay", "every command delayed by 15 periods, less than the time-out: the counter aliases",
           "SecOC freshness (the counter alone cannot see it), then time-out",
           lambda ctx: [{"type": "delay", "delay_s": 0.015, **_ON_CMD}],
           {False: Expect(undetected=True), True: Expect(reasons=("freshness",), failsafe=True)}),
    Threat("state_replay", "repetition",
           f"rogue node re-sends car {CAR}'s logged state frame (STATE_C3) of tick {REPLAY_FROM_TICK} every period "
           "(secured: with its logged authenticator STATE_AUTH_C3)",
           "alive counter; SecOC authenticator per state frame (full 32-bit freshness)",
           _state_replay,
           {False: Expect(reasons=("counter",), undetected=True),
            True: Expect(reasons=("counter", "authentication", "freshness"), unchanged=True)}),
    Threat("state_masquerade", "masquerade",
           f"rogue node sends car {CAR}'s state frame (STATE_C3: standstill at 0 m) with a valid CRC",
           "none without authentication; SecOC authenticator per state frame",
           lambda ctx: [_rogue(STATE_ID, _forged_state(ctx))],
           {False: Expect(reasons=("counter",), undetected=True),
            True: Expect(reasons=("counter", "authentication"), unchanged=True)}),
    Threat("masquerade", "masquerade",
           f"rogue node sends 0 N commands on car {CAR}'s identifier with a valid CRC",
           "none without authentication (the CRC is public); SecOC MAC",
           lambda ctx: [_rogue(CMD_ID, _forged_command(ctx))],
           {False: Expect(reasons=("counter",), undetected=True), True: Expect(reasons=("counter", "authentication"), unchanged=True)}),
]

BY_KEY = {t.key: t for t in THREATS}


def base_overrides(key_file: Path | None) -> dict[str, Any]:
    over: dict[str, Any] = {"duration_s": DURATION_S,
                            "safety": {"command_timeout_s": TIMEOUT_S, "failsafe_decel_mps2": 1.2, "latch": True}}
    if key_file is not None:
        over["security"] = {"key_file": str(key_file), "session": 1}
    return over


def _scenario(base: Path, key_file: Path | None, impairments: list[dict[str, Any]]):  # type: ignore[no-untyped-def]
    from canbrake.scenario import load_scenario

    over = base_overrides(key_file)
    over["bus"] = {"impairments": impairments}
    return load_scenario(base, overrides=over)


def _run(scn, out: Path) -> dict[str, Any]:  # type: ignore[no-untyped-def]
    from canbrake.run import run_scenario

    return run_scenario(scn, out, backend="inprocess", plots=False)


@dataclass
class Outcome:
    """One threat run compared with the clean run of the same security setting."""

    key: str
    secured: bool
    status: str
    ticks: int
    rejected: dict[str, int]
    verdict: str
    failsafe_first_s: float | None
    reaction_s: float | None            # fail-safe entry minus attack start
    unchanged: bool                     # signals.csv identical to the clean run's
    ticks_changed: int                  # periods where car 3's applied force differs from clean
    max_force_dev_n: float              # max |applied force - clean| on car 3
    max_deflection_m: float
    clean_max_deflection_m: float
    extra: dict[str, Any] = field(default_factory=dict)


def clean_run(base: Path, work: Path, key_file: Path | None) -> Path:
    """The clean (no impairment) run of a security setting, in ``work``."""
    out = work / ("clean_secured" if key_file else "clean")
    if not (out / "summary.json").exists():
        _run(_scenario(base, key_file, []), out)
    return out


def run_threat(threat: Threat, base: Path, work: Path, key_file: Path | None) -> Outcome:
    """Run ``threat`` (authenticated iff ``key_file``) and compare with the clean run."""
    from canbrake.analysis.summary import read_signals
    from canbrake.bus.codec import FrameCodec
    from canbrake.build import bus_layout

    clean = clean_run(base, work, key_file)
    scn0 = _scenario(base, key_file, [])
    ctx = Context(clean, key_file is not None, FrameCodec(bus_layout(scn0).database()))
    out = work / f"{threat.key}{'_secured' if key_file else ''}"
    s = _run(_scenario(base, key_file, threat.impairments(ctx)), out)
    a, c = read_signals(out / "signals.csv"), read_signals(clean / "signals.csv")
    n = min(len(a["t_s"]), len(c["t_s"])) - 1  # last row: final state, no command
    dev = np.abs(a[f"brake_applied_n_c{CAR}"][:n] - c[f"brake_applied_n_c{CAR}"][:n])
    defl = [k for k in a if k.startswith("deflection_m_k")]
    first = (s.get("failsafe") or {}).get("first_activation_s", {}).get(f"c{CAR}")
    sf = s["safety"]
    return Outcome(
        key=threat.key, secured=key_file is not None, status=s["status"], ticks=s["ticks"],
        rejected={k: v for k, v in sf["rejected"].items() if v}, verdict=sf["verdict"],
        failsafe_first_s=first, reaction_s=None if first is None else round(first - ATTACK_S, 9),
        unchanged=(out / "signals.csv").read_bytes() == (clean / "signals.csv").read_bytes(),
        ticks_changed=int((dev > 1e-6 * (1 + np.abs(c[f"brake_applied_n_c{CAR}"][:n]))).sum()),
        max_force_dev_n=float(dev.max()) if n > 0 else 0.0,
        max_deflection_m=float(max(np.abs(a[k]).max() for k in defl)),
        clean_max_deflection_m=float(max(np.abs(c[k]).max() for k in defl)),
        extra={"unknown_senders": sf["unknown_senders"], "flood": sf["flood"]["frames_on_unknown_ids"]})


def expected_failsafe_s(dt_s: float = 0.001) -> float:
    """Fail-safe entry when no valid command arrives from ATTACK_S on: the last valid command is
    tick ATTACK_S/T - 1, and the brake unit waits TIMEOUT_S/T periods after it (plant rule: age >
    timeout)."""
    last = round(ATTACK_S / dt_s) - 1
    return round((last + round(TIMEOUT_S / dt_s) + 1) * dt_s, 9)


def scenario_digest(base: Path) -> str:
    """Hash of the base scenario file and this module (reuse check of the report)."""
    h = hashlib.sha256(Path(base).read_bytes())
    h.update(Path(__file__).read_bytes())
    return h.hexdigest()[:16]


def outcome_json(o: Outcome) -> str:
    return json.dumps(o.__dict__, sort_keys=True)
