"""SecOC-style authentication (canbrake.bus.secoc) and the receiver checks (canbrake.bus.guard)."""
from __future__ import annotations

import os

import cantools
import pytest
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from canbrake.analysis.summary import read_signals
from canbrake.bus.codec import FrameCodec
from canbrake.bus.e2e import e2e_crc
from canbrake.bus.guard import FrameGuard, sync_verdict
from canbrake.build import bus_layout
from canbrake.bus.secoc import MAC_BYTES, SecOC, load_key, write_key
from canbrake.run import preflight, run_scenario
from canbrake.scenario import ScenarioError, load_scenario
from conftest import CASE1

KEY = bytes(range(16))


def build_database(scn):  # noqa: ANN001, ANN201 - the scenario's database (secured when security is set)
    return bus_layout(scn).database()


def test_mac_is_truncated_aes_cmac_over_id_freshness_and_body():
    s = SecOC(KEY, session=7)
    payload = bytes([0, 0x03, 0x10, 0x20, 0x30, 0, 0, 0])
    signed = s.sign(0x083, payload, 1234, has_crc=True)
    c = CMAC(algorithms.AES(KEY))
    c.update(b"\x83\x00" + (7).to_bytes(4, "big") + (1234).to_bytes(4, "big") + payload[1:5])
    assert signed[5:] == c.finalize()[:MAC_BYTES]
    assert signed[0] == e2e_crc(0x083, signed)  # CRC computed last, over the MAC
    assert s.verify(0x083, signed, 1234, has_crc=True)
    assert not s.verify(0x083, signed, 1234 + 15, has_crc=True)      # same counter, other tick
    assert not SecOC(KEY, session=8).verify(0x083, signed, 1234, has_crc=True)  # other run
    assert not s.verify(0x084, signed, 1234, has_crc=True)           # other identifier


def test_replay_of_an_aliasing_frame_is_stale_and_a_forgery_is_unauthentic():
    s = SecOC(KEY)
    codec = FrameCodec(build_database(load_scenario(CASE1, overrides={"security": {"key_file": "x"}})))
    enc = codec["BRAKE_CMD_C3"]
    old = s.sign(0x083, enc.encode({"BrakeForce": 1000.0}, counter=40 % 15), 40, has_crc=True)
    g = FrameGuard(s, max_lag=7)
    # at tick 55 the frame of tick 40 has the counter of tick 55: the counter alone accepts it
    assert FrameGuard(None, max_lag=7).origin(0x083, old, 55, 54) == 55
    assert g.origin(0x083, old, 55, 54, authenticated=True) is None and g.last_reason == "freshness"
    forged = enc.encode({"BrakeForce": 0.0}, counter=55 % 15)  # valid CRC, MAC bytes guessed as 0
    assert g.origin(0x083, forged, 55, 54, authenticated=True) is None and g.last_reason == "authentication"
    fresh = s.sign(0x083, enc.encode({"BrakeForce": 1000.0}, counter=55 % 15), 55, has_crc=True)
    assert g.origin(0x083, fresh, 55, 54, authenticated=True) == 55
    assert g.rejected["freshness"] == g.rejected["authentication"] == 1


def test_sync_is_accepted_only_in_sequence_and_when_the_tick_is_complete():
    g = FrameGuard()
    tick = lambda k: k.to_bytes(4, "little")  # noqa: E731
    assert sync_verdict(g, 0x10, tick(5), 4, tick_complete=True, lockstep=True) == "tick"
    assert sync_verdict(g, 0x10, tick(5), 4, tick_complete=False, lockstep=True) is None
    assert sync_verdict(g, 0x10, tick(9), 4, tick_complete=True, lockstep=True) is None
    assert sync_verdict(g, 0x10, tick(0xFFFFFFFF), 4, tick_complete=False, lockstep=True) is None
    assert sync_verdict(g, 0x10, tick(0xFFFFFFFF), 4, tick_complete=True, lockstep=True) == "end"
    assert g.rejected["sync"] == 3
    s = SecOC(KEY)
    gs = FrameGuard(s)
    end = tick(0xFFFFFFFF) + bytes(4)
    assert sync_verdict(gs, 0x10, end, 4, tick_complete=True, lockstep=True) is None  # unsigned END
    assert sync_verdict(gs, 0x10, s.sign(0x10, end, 4, has_crc=False), 4, tick_complete=True, lockstep=True) == "end"
    assert gs.rejected["authentication"] == 1


def test_secured_database_documents_the_mac_and_decodes_with_cantools():
    scn = load_scenario(CASE1, overrides={"security": {"key_file": "unused"}})
    db = cantools.database.load_string(build_database(scn).as_dbc_string())
    for name, length in (("BRAKE_CMD_C3", 8), ("SYNC", 8), ("STATE_DONE_C1", 5), ("CMD_DONE_C6", 5)):
        m = db.get_message_by_name(name)
        mac = m.get_signal_by_name("MAC")
        assert m.length == length and mac.start == 8 * (length - 3) and mac.length == 24
        assert "AES-128-CMAC" in mac.comment and "freshness" in mac.comment
    assert db.get_message_by_name("STATE_C3").length == 8 and "MAC" not in \
        [s.name for s in db.get_message_by_name("STATE_C3").signals]
    s = SecOC(KEY)
    data = s.sign(0x083, FrameCodec(build_database(scn))["BRAKE_CMD_C3"].encode({"BrakeForce": 12340.0}, counter=3),
                  3, has_crc=True)
    assert db.decode_message(0x083, data)["BrakeForce"] == 12340.0


@pytest.mark.parametrize("content,what", [(None, "no such key file"), (b"abc", "found 3 bytes"),
                                          (b"00" * 15, "found 30 bytes")])
def test_a_bad_key_file_is_one_clear_error(tmp_path, content, what):
    p = tmp_path / "k.hex"
    if content is not None:
        p.write_bytes(content)
    scn = load_scenario(CASE1, overrides={"security": {"key_file": str(p)}})
    with pytest.raises(ScenarioError, match=f"security.key_file: .*{what}"):
        preflight(scn, "inprocess")


def test_key_file_formats(tmp_path):
    k = write_key(tmp_path / "k")
    assert len(load_key(k)) == 16 and oct(k.stat().st_mode & 0o777) == "0o600"
    (tmp_path / "raw").write_bytes(KEY)
    assert load_key(tmp_path / "raw") == KEY


def test_authenticated_run_is_identical_to_plain_and_the_same_across_processes(tmp_path):
    """MACs change the frames, not the braking: signals.csv equals the unauthenticated run's, and
    the cross-process run (each node reads the key itself) gives the same files as in-process."""
    key = write_key(tmp_path / "key.hex")
    base = {"duration_s": 0.05, "safety": {"command_timeout_s": 0.01}}
    run_scenario(load_scenario(CASE1, overrides=base), tmp_path / "plain", backend="inprocess", plots=False)
    sec = load_scenario(CASE1, overrides={**base, "security": {"key_file": str(key)}})
    a = run_scenario(sec, tmp_path / "inprocess", backend="inprocess", plots=False)
    b = run_scenario(sec, tmp_path / "memory", backend="memory", plots=False)
    assert a["status"] == b["status"] == "ok" and a["safety"]["verdict"] == b["safety"]["verdict"] == "clean"
    for f in ("signals.csv", "frames.log"):
        assert (tmp_path / "memory" / f).read_bytes() == (tmp_path / "inprocess" / f).read_bytes()
    assert (tmp_path / "plain" / "signals.csv").read_bytes() == (tmp_path / "inprocess" / "signals.csv").read_bytes()
    assert (tmp_path / "plain" / "frames.log").read_bytes() != (tmp_path / "inprocess" / "frames.log").read_bytes()


def test_peer_hold_then_fallback_on_own_sensors(tmp_path):
    """Car 2's state frames lost from 0.02 s: with peer_hold_periods = 5 its peers drop its value
    after 5 periods and count one fallback entry each; their commands say Status 1 (degraded)."""
    over = {"duration_s": 0.05, "bus": {"impairments": [{"type": "loss", "probability": 1.0, "ids": [0x142],
                                                          "start_s": 0.02}]},
            "safety": {"peer_hold_periods": 5}}
    s = run_scenario(load_scenario(CASE1, overrides=over), tmp_path, backend="inprocess", plots=False)
    fb = s["safety"]["fallbacks"]
    assert fb["ecu_peer_loss_entries"] == 5  # every other ECU, once
    # the last state of car 2 is tick 19's; from tick 25 (age 6 > 5) to 49 its peers run without it
    assert fb["ecu_peer_loss_time_s"] == pytest.approx(5 * 25 * 0.001)
    assert read_signals(tmp_path / "signals.csv")["t_s"].size == 51
    import can

    codec = FrameCodec(build_database(load_scenario(CASE1)))["BRAKE_CMD_C1"]
    status = [codec.decode(m.data)["Status"] for m in can.LogReader(str(tmp_path / "frames.log"))
              if m.arbitration_id == 0x081]
    assert status == [0] * 25 + [1] * 25


def test_a_lost_state_frame_leaves_its_authenticator_orphaned_and_the_run_as_unsecured(tmp_path):
    """Secured: car 2's state frames lost from 0.02 s while their authenticators still arrive —
    each of its five listeners counts one orphaned authenticator per period (ticks 20..49), falls
    back as in the unsecured run, and braking equals the unsecured run's."""
    key = write_key(tmp_path / "key.hex")
    over = {"duration_s": 0.05, "bus": {"impairments": [{"type": "loss", "probability": 1.0, "ids": [0x142],
                                                          "start_s": 0.02}]},
            "safety": {"peer_hold_periods": 5}}
    plain = run_scenario(load_scenario(CASE1, overrides=over), tmp_path / "plain", backend="inprocess", plots=False)
    sec = run_scenario(load_scenario(CASE1, overrides={**over, "security": {"key_file": str(key)}}),
                       tmp_path / "sec", backend="inprocess", plots=False)
    assert sec["safety"]["state_auth_orphans"] == 5 * (50 - 20) and plain["safety"]["state_auth_orphans"] == 0
    assert sec["safety"]["fallbacks"] == plain["safety"]["fallbacks"]
    assert (tmp_path / "sec" / "signals.csv").read_bytes() == (tmp_path / "plain" / "signals.csv").read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("secured", [False, True], ids=["e2e", "secoc"])
def test_forged_end_frames_from_a_foreign_process_cannot_end_a_run(tmp_path, secured):
    """A rogue on the cross-process bus sends SYNC END (tick 0xFFFFFFFF) every 0.5 ms for the
    whole run: no node ends early (without SecOC an END counts only after the last scheduled tick,
    with SecOC only with its MAC), the run finishes every tick, the forgeries are counted."""
    import threading
    import time
    import uuid

    import can

    key = write_key(tmp_path / "key.hex")
    scn = load_scenario(CASE1, overrides={"duration_s": 0.05, "security": {"key_file": str(key)} if secured else None})
    channel = f"cbrogue-{uuid.uuid4().hex[:6]}"
    stop = threading.Event()
    sent = []

    def rogue() -> None:
        with can.Bus(interface="canbrake", channel=channel, can_filters=[{"can_id": 0x7FF, "can_mask": 0x7FF}]) as b:
            end = can.Message(arbitration_id=0x010, data=b"\xff\xff\xff\xff" + bytes(4 if secured else 0),
                              is_extended_id=False)
            while not stop.is_set():
                b.send(end)
                sent.append(1)
                time.sleep(0.0005)

    t = threading.Thread(target=rogue, daemon=True)
    t.start()
    try:
        s = run_scenario(scn, tmp_path / "run", backend="memory", channel=channel, plots=False, stall_timeout_s=20)
    finally:
        stop.set()
        t.join()
    assert s["status"] == "ok" and s["ticks"] == 50, s["message"]
    sf = s["safety"]
    assert len(sent) > 0 and sf["rejected"]["sync"] + sf["rejected"]["authentication"] + sf["end_frames_ignored"] > 0
    assert sf["verdict"] == "attack or fault detected"


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("backend", ["inprocess", "memory"])
def test_a_diverged_run_still_ends_though_its_early_end_frame_is_not_trusted(tmp_path, backend):
    """The paper's gains with a realistic brake and the paper's coupler without end stops diverge:
    the plant's unauthenticated early END is ignored by the other nodes, and the driver or the
    orchestrator ends them once the plant has finished; the run's verdict is "diverged", safety clean."""
    from canbrake.report.chen2023 import _PAPER_GAINS

    scn = load_scenario(CASE1, profile="realistic", overrides={"duration_s": 5.0, **_PAPER_GAINS,
                                                                "train.every_vehicle.coupler.end_stop_m": None})
    s = run_scenario(scn, tmp_path, backend=backend, plots=False)
    # status: how it executed (ok); verdict: the physics (issue 11, canbrake/analysis/verdict.py)
    assert s["status"] == "ok" and s["verdict"] == "diverged" and s["ticks"] < 500
    assert s["safety"]["end_frames_ignored"] == scn.n_cars + 1 and s["safety"]["verdict"] == "clean"


def test_a_command_page_without_room_for_the_mac_is_refused():
    from cantools.database.can import Database, Message, Signal

    sig = Signal(name="Force", start=16, length=40, byte_order="little_endian")
    db = Database(messages=[Message(frame_id=0x081, name="BRAKE_CMD_C1", length=7, signals=[sig])])
    from canbrake.bus.secoc import secure_database

    with pytest.raises(ValueError, match="BRAKE_CMD_C1 uses 7 bytes"):
        secure_database(db)


def test_a_missing_key_file_on_the_command_line_is_exit_2_one_message_nothing_written(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "canbrake.cli", "run", str(CASE1), "--set",
                        f"security.key_file={tmp_path / 'absent.hex'}", "--duration", "0.01", "--out", str(out),
                        "--no-plots"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0 and "security.key_file" in r.stderr and "no such key file" in r.stderr
    assert not out.exists()


def test_mac_is_aes_cmac_and_survives_pickling_after_use() -> None:
    """The per-frame MAC copies one keyed CMAC context: same bytes as a fresh CMAC over the
    documented input, and a SecOC object that has signed still pickles (node processes)."""
    import pickle

    from cryptography.hazmat.primitives.ciphers import algorithms
    from cryptography.hazmat.primitives.cmac import CMAC

    from canbrake.bus.secoc import SecOC

    key = bytes(range(16))
    s = SecOC(key, session=7)
    for tick in (0, 1, 2**32 + 5):
        ref = CMAC(algorithms.AES(key))
        ref.update(bytes((0x41, 0x01)) + (7).to_bytes(4, "big") + (tick & 0xFFFFFFFF).to_bytes(4, "big") + b"body")
        assert s.mac(0x141, tick, b"body") == ref.finalize()[:3]
    t = pickle.loads(pickle.dumps(s))
    assert t.mac(0x141, 3, b"x") == s.mac(0x141, 3, b"x")
