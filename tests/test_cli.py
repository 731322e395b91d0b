"""Bad input gets one clear message naming the field or file, exit status 2, no traceback,
and nothing already written is lost."""
from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import CASE1, ROOT


def canbrake(*args, cwd=None, input=None):
    return subprocess.run([sys.executable, "-m", "canbrake.cli", *args], capture_output=True, text=True,
                          cwd=cwd, input=input, timeout=300)


def _bad(r, *needles):
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "Traceback" not in r.stderr and "Traceback" not in r.stdout
    err = r.stderr.strip().splitlines()
    assert err and err[-1].startswith("canbrake: error:")
    for n in needles:
        assert n in r.stderr, r.stderr


def _scenario(tmp_path, text):
    p = tmp_path / "s.yaml"
    p.write_text(text)
    return p


BASE = CASE1.read_text()


@pytest.mark.parametrize("edit, needles", [
    (lambda t: t.replace("seed: 1", "seed: 1\nbogus_key: 3"), ["bogus_key", "unknown key"]),
    (lambda t: t.replace("mass_kg: [18000,", "mass_kg: [-18000,"), ["train.vehicles.0.mass_kg", "mass must be > 0"]),
    (lambda t: t.replace("speed_kmh: [88, 93, 87, 89, 92, 95.5]", "speed_kmh: [88, 93]"), ["initial.speed_kmh", "6 values"]),
    (lambda t: t.replace("k: 36", "k: 36\n    kk: 1"), ["controller.params.kk", "unknown parameter"]),
    (lambda t: t.replace("name: chen2023\n", "name: nosuch\n"), ["controller.name", "nosuch"]),
    (lambda t: t.replace("mode: lockstep", "mode: [lockstep"), ["malformed YAML", "line"]),
    (lambda t: t.replace("bitrate_bps: 1000000", "bitrate_bps: 1000000\n  impairments: [{type: loss, probability: 1.5}]"),
     ["bus.impairments", "probability"]),
])
def test_bad_scenarios(tmp_path, edit, needles):
    p = _scenario(tmp_path, edit(BASE))
    _bad(canbrake("run", str(p), "--out", str(tmp_path / "out")), str(p), *needles)


def test_missing_scenario_file(tmp_path):
    _bad(canbrake("run", str(tmp_path / "nope.yaml")), "nope.yaml", "no such scenario file")


def test_unknown_profile(tmp_path):
    _bad(canbrake("run", str(CASE1), "--profile", "nosuch", "--out", str(tmp_path)), "profile 'nosuch'", "realistic")


def test_bad_set_override(tmp_path):
    _bad(canbrake("run", str(CASE1), "--set", "duration_s", "--out", str(tmp_path)), "KEY=VALUE")
    _bad(canbrake("run", str(CASE1), "--set", "duration_s=-1", "--out", str(tmp_path)), "duration_s")


def test_dbc_that_does_not_match_the_scenario(tmp_path):
    other = tmp_path / "four.dbc"
    assert canbrake("dbc", "--cars", "4", "-o", str(other)).returncode == 0
    _bad(canbrake("run", str(CASE1), "--dbc", str(other), "--out", str(tmp_path / "o")), "four.dbc", "4 cars", "6")
    broken = tmp_path / "broken.dbc"
    broken.write_text("this is not a DBC file {")
    _bad(canbrake("run", str(CASE1), "--dbc", str(broken), "--out", str(tmp_path / "o")), "broken.dbc")


def test_missing_vcan_interface_is_explained(tmp_path):
    r = canbrake("run", str(CASE1), "--bus", "socketcan", "--channel", "vcan7", "--out", str(tmp_path / "o"))
    _bad(r, "vcan7")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("args, needles", [
    (["--interface", "nosuch"], ["--interface nosuch", "not a python-can interface", "pcan"]),
    (["--interface", "virtual"], ["--interface virtual", "--bus virtual"]),
    # no PCAN driver on a test machine: python-can's own reason, after the option that caused it
    (["--interface", "pcan", "--channel", "PCAN_USBBUS1"], ["--interface pcan --channel PCAN_USBBUS1",
                                                           "cannot open the python-can bus"]),
    (["--set", "bus.interface_args.fd=true"], ["bus.interface_args", "--interface NAME"]),
])
def test_bad_adapter_choice_is_explained(tmp_path, args, needles):
    _bad(canbrake("run", str(CASE1), *args, "--out", str(tmp_path / "o")), *needles)
    assert not (tmp_path / "o").exists()


def test_adapter_gets_channel_bitrate_and_interface_args(monkeypatch):
    """--interface NAME: channel, bus.bitrate_bps (as python-can's ``bitrate``) and
    bus.interface_args reach ``can.Bus`` in every node process; interface_args wins."""
    import can

    from canbrake import run
    from canbrake.scenario import load_scenario

    scn = load_scenario(CASE1, overrides={"bus": {"bitrate_bps": 250000, "interface_args": {"fd": False}}})
    choice = run.choose_bus(scn, interface="kvaser", channel="0")
    assert (choice.backend, choice.interface, choice.channel, choice.log_channel) == ("adapter", "kvaser", "0", "0")
    opened: list[dict] = []
    monkeypatch.setattr(can, "Bus", lambda **kw: opened.append(kw) or "bus")
    assert run._open_bus(choice, [{"can_id": 0x80, "can_mask": 0x7FF}], "ecu") == "bus"
    assert opened == [{"interface": "kvaser", "channel": "0", "can_filters": [{"can_id": 0x80, "can_mask": 0x7FF}],
                       "receive_own_messages": False, "bitrate": 250000, "fd": False}]
    scn2 = load_scenario(CASE1, overrides={"bus": {"interface_args": {"bitrate": 125000}}})
    assert run.choose_bus(scn2, interface="pcan").bus_kwargs == {"bitrate": 125000}


def test_nothing_already_written_is_lost(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text('{"keep": true}')
    p = _scenario(tmp_path, BASE.replace("seed: 1", "seed: -4"))
    _bad(canbrake("run", str(p), "--out", str(out)), "seed")
    assert (out / "summary.json").read_text() == '{"keep": true}'


def test_decode_corrupt_and_missing_logs(tmp_path):
    _bad(canbrake("decode", str(tmp_path / "nope.log")), "nope.log")
    bad = tmp_path / "bad.log"
    bad.write_text("(0.000100) vcan0 141#0011223344556677\n(garbage line without a frame\n")
    r = canbrake("decode", str(bad), "--dbc", str(ROOT / "dbc" / "canbrake.dbc"))
    assert r.returncode in (0, 2) and "Traceback" not in r.stderr
    _bad(canbrake("decode", str(bad), "--dbc", str(tmp_path / "missing.dbc")), "missing.dbc")


def test_decode_reads_candump_from_stdin():
    r = canbrake("decode", "-", "--dbc", str(ROOT / "dbc" / "canbrake.dbc"),
                 input="(1700000000.000100) vcan0 010#2A000000\n(1700000000.000200) vcan0 7FF#00\n")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert "SYNC(Tick: 42 tick)" in lines[0] and lines[1].endswith("::")


def test_dbc_cli_rejects_bad_car_count():
    _bad(canbrake("dbc", "--cars", "0"), "--cars")
