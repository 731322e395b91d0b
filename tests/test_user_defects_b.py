"""Defects found trying canbrake as a user (issue 28, "found this turn" 6, 7 and 9): log formats
on any channel name, a user's controller by name, the papers' headline metrics in summary.json."""
from __future__ import annotations

import collections

import can
import pytest

from canbrake.run import choose_bus, run_scenario
from canbrake.scenario import load_scenario

from conftest import CASE1, SCENARIOS

SEGMENTED = SCENARIOS / "chen2023_case1_segmented.yaml"
NUMBERED = ["asc", "blf", "trc", "mf4"]


def _asammdf() -> bool:
    try:
        import asammdf  # noqa: F401
    except ImportError:
        return False
    return True


def _file_channel(fmt: str, channel: int) -> int:
    """The channel number written in the file, from the one python-can's reader gives back: the
    ASC and BLF readers subtract 1 (python-can counts from 0), the TRC and MF4 readers do not."""
    return channel + 1 if fmt in ("asc", "blf") else channel


def _skip_without_asammdf(fmt: str) -> None:
    if fmt == "mf4" and not _asammdf():
        pytest.skip("asammdf not installed (pip install 'canbrake[mf4]')")


# ------------------------------------------------------------------ 6. log formats, channel numbers
@pytest.mark.parametrize("channel", ["train999", "train", "cb4242-0a1962"])
@pytest.mark.parametrize("fmt", NUMBERED)
def test_numbered_formats_write_channel_1_whatever_the_channel_name(tmp_path, fmt, channel):
    """One bus is CAN 1 in .asc/.blf/.trc/.mf4, whether the channel's name ends in digits or not
    (python-can's writers would read ``train999`` as channel 999: MF4's uint8 overflowed)."""
    _skip_without_asammdf(fmt)
    scn = load_scenario(CASE1, overrides={"duration_s": 0.003, "bus.log_format": fmt})
    s = run_scenario(scn, tmp_path / "r", backend="inprocess", channel=channel, plots=False)
    assert s["status"] == "ok", s.get("message")
    msgs = list(can.LogReader(str(tmp_path / "r" / f"frames.{fmt}")))
    assert len(msgs) > 20
    assert {_file_channel(fmt, m.channel) for m in msgs} == {1}
    if fmt == "asc":  # the channel column of the file itself
        rows = [ln.split() for ln in (tmp_path / "r" / "frames.asc").read_text().splitlines()]
        assert {r[1] for r in rows if len(r) > 3 and r[2] == "10"} == {"1"}


@pytest.mark.parametrize("fmt", NUMBERED)
def test_bus_segments_are_channels_1_to_n_in_scenario_order(tmp_path, fmt):
    """With bus segments each segment is its own channel, numbered 1..n in the scenario's order
    (``backbone`` 1, ``car1`` 2, ...), the same number in the merged log and the segment's own; the
    summary says which segment is which number."""
    _skip_without_asammdf(fmt)
    scn = load_scenario(SEGMENTED, overrides={"duration_s": 0.02, "bus.log_format": fmt})
    out = tmp_path / "r"
    s = run_scenario(scn, out, backend="inprocess", plots=False)
    assert s["status"] == "ok", s.get("message")
    segs = s["bus_load"]["segments"]
    names = [seg.name for seg in scn.bus.segments]
    assert [segs[n]["channel"] for n in names] == list(range(1, len(names) + 1))
    merged = collections.defaultdict(list)
    for m in can.LogReader(str(out / f"frames.{fmt}")):
        merged[_file_channel(fmt, m.channel)].append(m)
    assert set(merged) == set(range(1, len(names) + 1))
    tol = 1.1e-4 if fmt == "trc" else 1.1e-6  # each format's time resolution (TRC: 0.1 ms)
    for n in names:  # channel k of the merged log is segment k's own log, frame for frame
        own = list(can.LogReader(str(out / segs[n]["log"])))
        assert {_file_channel(fmt, m.channel) for m in own} == {segs[n]["channel"]}, n
        mine = merged[segs[n]["channel"]]
        assert [(m.arbitration_id, bytes(m.data)) for m in mine] == [(m.arbitration_id, bytes(m.data)) for m in own]
        assert max(abs(a.timestamp - b.timestamp) for a, b in zip(mine, own)) <= tol, n


def test_candump_log_names_one_fixed_interface_on_the_memory_buses(tmp_path):
    """frames.log's interface column is ``canbrake0`` on the in-memory, virtual and in-process
    buses, whatever the channel (the CLI passes the random in-memory channel it printed), so the
    README's ``canplayer -I frames.log vcan0=canbrake0`` replays it; SocketCAN keeps its interface."""
    from canbrake.cli import main

    scn = load_scenario(CASE1)
    for backend in ("memory", "virtual", "inprocess"):
        for channel in (None, "train999", "cb4242-0a1962"):
            assert choose_bus(scn, backend, channel).log_channel == "canbrake0", (backend, channel)
    assert choose_bus(scn, "socketcan", "vcan3").log_channel == "vcan3"
    out = tmp_path / "r"
    assert main(["run", str(CASE1), "--bus", "inprocess", "--channel", "train7", "--duration", "0.003",
                 "--no-plots", "--out", str(out)]) == 0
    assert {ln.split()[1] for ln in (out / "frames.log").read_text().splitlines()} == {"canbrake0"}
    assert {m.channel for m in can.LogReader(str(out / "frames.log"))} == {"canbrake0"}


# ------------------------------------------------------------------ 7. a user's controller by name
ACME = '''
from canbrake.control.base import ControlOutput, Controller


class AcmePD(Controller):
    """A user's speed PD (kp 1/s): each car tracks v* alone, nothing holds the couplers."""

    def __init__(self, car_index, n_cars, mass_kg, dt_s, *, kp: float = 2.0):
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        self.kp = kp

    def step(self, obs):
        return ControlOutput(self.mass_kg * (obs.ref_decel_mps2 + self.kp * (obs.speed_mps - obs.ref_speed_mps)))
'''


@pytest.fixture
def acme(tmp_path, monkeypatch):
    """``pip install acme`` as a test can do it: the package and its dist-info declaring
    ``acme_pd`` in the ``canbrake.controllers`` entry points, on sys.path."""
    import sys

    site = tmp_path / "site"
    (site / "acme").mkdir(parents=True)
    (site / "acme" / "__init__.py").write_text(ACME)
    info = site / "acme-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: acme\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[canbrake.controllers]\nacme_pd = acme:AcmePD\n")
    monkeypatch.syspath_prepend(str(site))
    yield "acme_pd"
    sys.modules.pop("acme", None)
    from canbrake.control import base

    base._REGISTRY.pop("acme_pd", None)


def test_switching_the_controller_by_name_drops_the_previous_parameters(acme, tmp_path):
    """``--set controller.name=acme_pd`` on Chen's scenario runs acme_pd with its own defaults (not
    Chen's alpha1...), with parameters given beside the switch; Chen's theta bounds stay the
    scenario's deflection bound; no profile brings Chen's parameters back (file, API, Scenario)."""
    import canbrake
    from canbrake.cli import main
    from canbrake.run import check_controller_params

    scn = load_scenario(CASE1, overrides={"controller.name": acme})
    assert scn.controller.name == acme and scn.controller.params == {}
    check_controller_params(scn)  # "controller.params.alpha1: unknown parameter" before
    assert scn.safety.max_abs_deflection_m == 0.01  # Chen's theta_lower_m/theta_upper_m: the scenario's bound
    scn = load_scenario(CASE1, overrides={"controller.name": acme, "controller.params.kp": 3})
    assert scn.controller.params == {"kp": 3}
    for profile in ("paper", "realistic"):
        scn = load_scenario(CASE1, profile=profile, overrides={"controller.name": acme})
        assert scn.controller.params == {} and scn.profile == profile, profile
        check_controller_params(scn)
        api = canbrake.load_scenario("chen2023_case1_fine_rail", profile=profile, controller__name=acme)
        assert api.controller.params == {}, profile
        # a profile applied later to the derived scenario does not bring Chen's parameters back
        again = canbrake.load_scenario(api, profile="realistic")
        assert again.controller.name == acme and again.controller.params == {}
        assert again.control_period_s == 0.01 and again.actuator.model == "realistic"  # the rest applies
    kept = load_scenario(CASE1, profile="realistic", overrides={"controller.params.k": 2.0})  # no switch
    assert kept.controller.name == "chen2023" and kept.controller.params["alpha1"] == 0.15
    assert kept.controller.params["k"] == 2.0
    r = canbrake.run("chen2023_case1_fine_rail", bus="inprocess", profile="realistic", duration_s=0.02,
                     plots=False, out=tmp_path / "api", controller__name=acme)
    assert r.status == "ok" and r.scenario.controller.params == {}
    assert main(["run", str(CASE1), "--bus", "inprocess", "--set", f"controller.name={acme}", "--duration", "0.005",
                 "--no-plots", "--out", str(tmp_path / "cli")]) == 0


def test_unknown_controller_lists_entry_point_controllers(acme, capsys, tmp_path):
    from canbrake.cli import main

    code = main(["run", str(CASE1), "--bus", "inprocess", "--set", "controller.name=acme_typo", "--duration",
                 "0.005", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 2 and "unknown controller 'acme_typo'" in err
    listed = err.split("available:")[1].split("\n")[0]
    assert "acme_pd" in listed and "chen2023" in listed, err


def test_every_controller_is_judged_against_the_scenario_bounds(acme, tmp_path):
    """acme_pd on Chen's case 1 (cars 88..95.5 km/h, nothing holds the couplers) compresses them
    by centimetres: verdict ``unsafe`` against the scenario's ±1 cm (Chen's theta, kept when the
    controller was switched), and the deflection plot draws that bound; a scenario without any
    bound draws none."""
    from canbrake.analysis.plots import plot_meta
    from canbrake.analysis.verdict import deflection_bound_m

    scn = load_scenario(CASE1, overrides={"controller.name": acme, "duration_s": 0.3, "safety.max_speed_kmh": 91})
    s = run_scenario(scn, tmp_path / "r", backend="inprocess", plots=False)
    assert s["status"] == "ok"
    unsafe = {f["quantity"]: f for f in s["findings"] if f["kind"] == "unsafe"}
    assert s["verdict"] == "unsafe" and set(unsafe) == {"deflection", "speed"}, s["findings"]
    assert unsafe["deflection"]["bound_m"] == 0.01 and unsafe["deflection"]["max_abs_deflection_m"] > 0.01
    assert unsafe["speed"]["bound_kmh"] == 91
    assert plot_meta(scn).bound_m == deflection_bound_m(scn) == 0.01
    bare = load_scenario(SCENARIOS / "li2024_pid.yaml")
    assert deflection_bound_m(bare) is None and plot_meta(bare).bound_m is None
    mine = load_scenario(CASE1, overrides={"controller.name": acme, "safety.max_abs_deflection_m": 0.05})
    assert plot_meta(mine).bound_m == deflection_bound_m(mine) == 0.05


# ------------------------------------------------------------------ 9. the papers' headline figures
def test_cai_run_reports_the_position_error_over_the_run(tmp_path, capsys):
    """Cai 2014's headline (Fig. 7) is the position error x − x* of the train: summary.json has its
    mean and max |e| over the run (the paper's window, the whole run), and the console prints them."""
    import numpy as np

    from canbrake.analysis.summary import read_signals
    from canbrake.cli import main

    out = tmp_path / "cai"
    assert main(["run", str(SCENARIOS / "cai2014_case1.yaml"), "--bus", "inprocess", "--duration", "0.3",
                 "--no-plots", "--out", str(out)]) == 0
    console = capsys.readouterr().out
    import json

    lead = json.loads((out / "summary.json").read_text())["metrics"]["lead_vehicle"]
    cols = read_signals(out / "signals.csv")
    e = np.abs(cols["position_m_c1"] - cols["ref_position_m"])
    assert lead["vehicle"] == 1 and lead["position_error_window_s"] == [0.0, 0.3]
    assert lead["position_error_mean_abs_m"] == pytest.approx(float(np.mean(e)), rel=1e-12)
    assert lead["position_error_max_abs_m"] == pytest.approx(float(np.max(e)), rel=1e-12)
    assert 0 < lead["position_error_mean_abs_m"] < lead["position_error_max_abs_m"]
    mm = lambda x: f"{x * 1000:.3g} mm"  # noqa: E731
    assert (f"position error x - x* (lead vehicle, 0-0.3 s): mean |e| {mm(lead['position_error_mean_abs_m'])}  "
            f"max |e| {mm(lead['position_error_max_abs_m'])}") in console, console


def test_li_run_names_the_lead_vehicles_speed_rmse(tmp_path, capsys):
    """Li 2024's Table 2 is the locomotive's (vehicle 1's) speed RMSE: summary.json names it beside the
    per-vehicle list and the console prints it beside the worst car's."""
    import json

    import numpy as np

    from canbrake.analysis.summary import read_signals
    from canbrake.cli import main

    out = tmp_path / "li"
    assert main(["run", str(SCENARIOS / "li2024_pid.yaml"), "--bus", "inprocess", "--duration", "0.3",
                 "--no-plots", "--out", str(out)]) == 0
    console = capsys.readouterr().out
    m = json.loads((out / "summary.json").read_text())["metrics"]
    cols = read_signals(out / "signals.csv")
    rmse = float(np.sqrt(np.mean(((cols["speed_mps_c1"] - cols["ref_speed_mps"]) * 3.6) ** 2)))
    lead = m["lead_vehicle"]
    assert lead["vehicle"] == 1 and lead["speed_rmse_kmh"] == pytest.approx(rmse, rel=1e-12)
    assert lead["speed_rmse_kmh"] == m["speed_rmse_kmh"][0] != max(m["speed_rmse_kmh"])
    assert "position_error_mean_abs_m" not in lead  # Li's scenario has no reference position
    assert (f"{max(m['speed_rmse_kmh']):.3g} km/h (worst car), {lead['speed_rmse_kmh']:.3g} km/h (lead vehicle)"
            in console), console


def test_a_derived_controller_keeps_the_parameters_it_accepts():
    """chen2023_compensated derives from chen2023 and accepts all of its parameters: switching to it
    by name (as the delay report's sweeps do) keeps the gains of the scenario and of its profile;
    back to chen2023 keeps those chen2023 accepts."""
    base = load_scenario(CASE1, profile="realistic")
    comp = load_scenario(CASE1, profile="realistic", overrides={"controller.name": "chen2023_compensated"})
    assert comp.controller.params == base.controller.params and comp.controller.params["alpha1"] == 0.15
    assert comp.profiles == base.profiles and comp.safety.max_abs_deflection_m is None
    back = load_scenario(CASE1, overrides={"controller.name": "chen2023_compensated",
                                           "controller.params.predict": False})
    from canbrake.scenario import resolve

    data = back.model_dump(mode="json")
    chen = resolve(data, "<t>", overrides={"controller.name": "chen2023"})
    assert "predict" not in chen.controller.params and chen.controller.params["alpha1"] == 120


def test_an_ecus_own_controller_switched_by_name_drops_the_old_ones_parameters():
    """``--set ecus.0.controller.name=X`` switches that ECU's own controller as ``controller.name``
    does the top-level one: the previous controller's parameters go (li2024_pid's
    airbrake_schedule), parameters given with the switch stay, and the top-level controller is
    untouched."""
    li = SCENARIOS / "li2024_pid.yaml"
    scn = load_scenario(li, overrides={"ecus.0.controller.name": "pi"})
    assert scn.ecus[0].controller.name == "pi" and scn.ecus[0].controller.params == {}
    scn = load_scenario(li, overrides={"ecus.0.controller.name": "pi", "ecus.0.controller.params.kp": 3})
    assert scn.ecus[0].controller.params == {"kp": 3}
    assert scn.controller == load_scenario(li).controller
