"""Car 3's brake ECU as a program of your own: plain python-can + cantools, no canbrake import.

canbrake runs the train, the bus and the other cars' ECUs; this program is ECU ``ecu3`` of
examples/foreign_ecu.yaml (``external: true``) and follows docs/lockstep-protocol.md:

    python -m canbrake run examples/foreign_ecu.yaml --channel train0 --out runs/fe &
    python examples/foreign_ecu.py --channel train0 --dbc runs/fe/canbrake.dbc

(``-i socketcan -c vcan0`` with ``--bus socketcan --channel vcan0`` on a vcan; any scenario whose
ecu3 runs the ``pi`` controller works: ``--external ecu3`` makes it external from the command line.)

Per control period k the plant sends SYNC(k), REFERENCE and SENSOR_C3; on SENSOR_C3 this ECU sends
(a heartbeat every heartbeat period), STATE_C3 and STATE_DONE_C3(k), then BRAKE_CMD_C3 and CMD_DONE_C3(k).
It ends on SYNC(0xFFFFFFFF). The control law is a PI speed controller with feed-forward:
F = m (a* + kp (v - v*)) N, + = brake (Chen's u_i3 term alone).
"""
from __future__ import annotations

import argparse
import time

import can
import cantools

END_TICK = 0xFFFFFFFF
COUNTER_MODULO = 15  # E2E alive counter: tick mod 15 (0..14)


def crc8_j1850(data: bytes) -> int:
    """CRC-8 SAE J1850: polynomial 0x1D, initial value 0xFF, final XOR 0xFF."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def protect(frame_id: int, payload: bytes) -> bytes:
    """E2E: byte 0 = CRC over the frame id (low byte, high byte) and payload bytes 1..end."""
    body = bytearray(payload)
    body[0] = crc8_j1850(bytes([frame_id & 0xFF, (frame_id >> 8) & 0xFF]) + bytes(body[1:]))
    return bytes(body)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-i", "--interface", default="canbrake", help="python-can interface (canbrake, socketcan, ...)")
    ap.add_argument("-c", "--channel", required=True, help="the run's channel (train0, vcan0, ...)")
    ap.add_argument("--dbc", required=True, help="the run's DBC (canbrake dbc SCENARIO, or RUN/canbrake.dbc)")
    ap.add_argument("--car", default="C3", help="message suffix of this ECU (C3 = ecu3 on vehicle 3)")
    ap.add_argument("--mass-kg", type=float, default=19500.0, help="this car's mass (kg)")
    ap.add_argument("--kp", type=float, default=36.0, help="speed gain (1/s)")
    ap.add_argument("--timeout", type=float, default=60.0, help="give up after this long without a SYNC (s)")
    a = ap.parse_args()

    db = cantools.database.load_file(a.dbc)
    msg = {name: db.get_message_by_name(f"{name}_{a.car}")
           for name in ("SENSOR", "STATE", "STATE_DONE", "BRAKE_CMD", "CMD_DONE", "HEARTBEAT")}
    sync, ref = db.get_message_by_name("SYNC"), db.get_message_by_name("REFERENCE")
    # the DBC gives the period: SYNC's cycle time is the control period, HEARTBEAT's the heartbeat's (ms)
    heartbeat_every = max(1, round(msg["HEARTBEAT"].cycle_time / sync.cycle_time))
    wanted = [sync.frame_id, ref.frame_id, msg["SENSOR"].frame_id]
    bus = can.Bus(interface=a.interface, channel=a.channel, receive_own_messages=False,
                  can_filters=[{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in wanted])

    def send(m: cantools.database.can.Message, data: bytes) -> None:
        bus.send(can.Message(arbitration_id=m.frame_id, data=data, is_extended_id=False))

    def encode(m: cantools.database.can.Message, values: dict) -> bytes:
        return m.encode(values, scaling=True, strict=False)

    k = -1                  # the tick of the newest SYNC; -1: the run has not started
    v_ref = a_ref = 0.0
    heard = time.monotonic()
    answered = 0            # periods this ECU answered
    try:
        while True:
            frame = bus.recv(timeout=0.1)
            if frame is None:
                if k < 0:   # before the first SYNC: announce ourselves (the run waits for this heartbeat)
                    send(msg["HEARTBEAT"], encode(msg["HEARTBEAT"], {"NodeState": 127}))
                if time.monotonic() - heard > a.timeout:
                    raise SystemExit(f"no SYNC on {a.channel} for {a.timeout:g} s")
                continue
            heard = time.monotonic()
            if frame.arbitration_id == sync.frame_id:
                k = sync.decode(frame.data)["Tick"]
                if k == END_TICK:
                    break
            elif frame.arbitration_id == ref.frame_id:
                r = ref.decode(frame.data)
                v_ref, a_ref = r["RefSpeed"], r["RefDecel"]
            elif frame.arbitration_id == msg["SENSOR"].frame_id and k >= 0:
                s = msg["SENSOR"].decode(frame.data)
                counter = k % COUNTER_MODULO
                # phase 1: heartbeat, state for the peers that listen to us, state barrier
                if k % heartbeat_every == 0:
                    send(msg["HEARTBEAT"], encode(msg["HEARTBEAT"], {"NodeState": 5}))
                state = {"Speed": s["Speed"], "Position": s["Position"], "Counter": counter, "CRC": 0}
                send(msg["STATE"], protect(msg["STATE"].frame_id, encode(msg["STATE"], state)))
                send(msg["STATE_DONE"], encode(msg["STATE_DONE"], {"Tick": k & 0xFFFF}))
                # phase 2: the control law, the command, the command barrier
                force_n = a.mass_kg * (a_ref + a.kp * (s["Speed"] - v_ref))
                cmd = {"BrakeForce": force_n, "Status": 0, "Counter": counter, "CRC": 0}
                send(msg["BRAKE_CMD"], protect(msg["BRAKE_CMD"].frame_id, encode(msg["BRAKE_CMD"], cmd)))
                send(msg["CMD_DONE"], encode(msg["CMD_DONE"], {"Tick": k & 0xFFFF}))
                answered += 1
    finally:
        bus.shutdown()
    print(f"{a.car}: answered {answered} control periods, the run ended")


if __name__ == "__main__":
    main()
