"""Defects found trying canbrake as a new user (issue 28): each test failed before its fix."""
from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import CASE1, ROOT


# ----------------------------------------------------------------------------- a disk that fills
def _small_fs_works() -> bool:
    """A private mount namespace with a tmpfs of our own (unshare; root or user namespaces)."""
    if shutil.which("unshare") is None:
        return False
    r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                        "mount -t tmpfs -o size=64k tmpfs /mnt"], capture_output=True, timeout=30)
    return r.returncode == 0


def _valid_files(run: Path) -> list[str]:
    """The files of a run directory that a reader could not take as they are: left-over
    temporary files, JSON that does not parse, CSV/log text with a line cut short."""
    import can
    import cantools
    import yaml

    bad = []
    for p in sorted(run.rglob("*")):
        if p.is_dir():
            continue
        rel = str(p.relative_to(run))
        data = p.read_bytes()
        if ".tmp" in p.name:
            bad.append(f"{rel}: a temporary file left behind")
        elif p.suffix == ".json":
            try:
                json.loads(data)
            except ValueError:
                bad.append(f"{rel}: not JSON ({len(data)} bytes)")
        elif p.suffix in (".csv", ".log") and data and not data.endswith(b"\n"):
            bad.append(f"{rel}: last line cut short")
        elif p.suffix == ".csv" and data:
            rows = list(csv.reader(data.decode().splitlines()))
            if any(len(r) != len(rows[0]) for r in rows):
                bad.append(f"{rel}: rows of different widths")
        elif p.parent == run and p.suffix == ".log":
            n, lines = sum(1 for _ in can.LogReader(str(p))), data.count(b"\n")
            if n != lines:
                bad.append(f"{rel}: {lines} lines but {n} frames")
        elif p.suffix == ".log" and not data:
            bad.append(f"{rel}: an empty log")
        elif p.suffix == ".yaml":
            yaml.safe_load(data)
        elif p.suffix == ".dbc":
            cantools.database.load_string(data.decode())
    return bad


@pytest.mark.parametrize("bus", ["memory", "inprocess"])
def test_a_disk_that_fills_during_a_run_gives_one_line_and_valid_files(tmp_path, bus):
    """The run directory on a 160 kB file system: frames.log fills it within the first simulated
    second. The recorder's flush fails with ENOSPC, then a node process must not print a
    traceback (it used to, when writing its own log to the same full disk failed too); the one
    line names the full disk, and every file left in the run directory is whole."""
    if not _small_fs_works():
        pytest.skip("no private mount namespace here (unshare --user --mount)")
    keep = tmp_path / "kept"
    script = (f"mount -t tmpfs -o size=160k tmpfs {tmp_path / 'mnt'} || exit 99; "
              f"{sys.executable} -m canbrake.cli run {CASE1} --bus {bus} --duration 3 --no-plots "
              f"--out {tmp_path / 'mnt' / 'run'}; rc=$?; cp -a {tmp_path / 'mnt' / 'run'} {keep}; exit $rc")
    (tmp_path / "mnt").mkdir()
    r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 1, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("canbrake: error:")]
    assert len(errors) == 1 and "No space left on device" in errors[0], r.stderr
    others = [ln for ln in r.stderr.splitlines() if ln not in errors]
    assert not [ln for ln in others if any(w in ln for w in ("Traceback", "Error", "Exception", "Errno"))], r.stderr
    assert not any(ln.startswith(("Process ", "  File ")) for ln in others), r.stderr
    assert (keep / "scenario.yaml").exists() and (keep / "frames.log").stat().st_size > 0
    assert _valid_files(keep) == []


def test_temporary_files_of_killed_node_processes_are_removed_once_they_are_reaped(tmp_path):
    """A node process killed while it wrote a file atomically (write_text_atomic: its log, its
    statistics) leaves ``.NAME.tmpPID``; once the run's processes are reaped the orchestrator
    removes those of its own children (seen under load: a full disk, the plant killed while it
    wrote logs/plant.log), and nothing else."""
    from canbrake.run import drop_temp_files

    (tmp_path / "logs").mkdir()
    (tmp_path / "processes").mkdir()
    left = [tmp_path / "logs" / ".plant.log.tmp123", tmp_path / ".plant_stats.json.tmp123",
            tmp_path / "processes" / ".ecu3.json.tmp456"]
    kept = [tmp_path / ".summary.json.tmp999", tmp_path / "signals.csv", tmp_path / "logs" / "plant.log",
            tmp_path / "plant.tmp123"]
    for f in left + kept:
        f.write_text("x")
    assert sorted(drop_temp_files(tmp_path, [123, 456])) == sorted(str(f.relative_to(tmp_path)) for f in left)
    assert not any(f.exists() for f in left) and all(f.exists() for f in kept)
    assert drop_temp_files(tmp_path, []) == [] and drop_temp_files(tmp_path / "none", [1]) == []
    # the writers' own temporary name (one definition: canbrake.atomic) is what it removes
    from canbrake.atomic import temp_path

    mine = temp_path(tmp_path / "logs" / "ecu1.log")
    mine.write_text("x")
    assert drop_temp_files(tmp_path, [os.getpid()]) == [str(mine.relative_to(tmp_path))]


# ----------------------------------------------------------------------------- control period bound
def test_a_control_period_no_can_bus_can_carry_is_refused():
    """Every period begins with the 4-byte SYNC frame (95 bit times with worst-case stuffing and
    the interframe space): a shorter period is refused, naming the field, the bound and the bit
    rate it follows from (the slowest the SYNC crosses); every built-in scenario is above it."""
    from canbrake.builtin import builtin_scenarios
    from canbrake.scenario import ScenarioError, load_scenario

    with pytest.raises(ScenarioError, match=r"control_period_s: 1e-09 s is shorter .* 95 bit times .* "
                                            r"= 95 us at 1000 kbit/s \(bus.bitrate_bps\)"):
        load_scenario(CASE1, overrides={"control_period_s": 1e-9, "duration_s": 0.01})
    assert load_scenario(CASE1, overrides={"control_period_s": 95e-6, "duration_s": 0.01}).n_ticks == 105
    with pytest.raises(ScenarioError, match=r"at least 190 us"):
        load_scenario(CASE1, overrides={"control_period_s": 150e-6, "bus.bitrate_bps": 500_000, "duration_s": 0.01})
    seg = ROOT / "scenarios" / "chen2023_case1_segmented.yaml"  # car segments at 1 Mbit/s, backbone at 500 kbit/s
    with pytest.raises(ScenarioError, match=r"190 us at 500 kbit/s \(bus\.segments\.\d+\.bitrate_bps\)"):
        load_scenario(seg, overrides={"control_period_s": 150e-6})
    for b in builtin_scenarios():
        for profile in [None, *load_scenario(b.path).profiles]:
            scn = load_scenario(b.path, profile=profile)
            assert scn.control_period_s >= scn.min_control_period_s()[0], (b.name, profile)


# ----------------------------------------------------------------------------- built-in names everywhere
BUILTIN = "chen2023_case1_fine_rail"


def test_dbc_analyze_and_sweep_take_a_built_in_scenario_name(tmp_path, monkeypatch, capsys):
    """`canbrake run NAME` took a built-in scenario's name; dbc, analyze and sweep said "no such
    scenario file". Run from an empty directory, so no scenarios/ folder can stand in for it."""
    import cantools

    from canbrake.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["dbc", BUILTIN, "-o", "case1.dbc"]) == 0, capsys.readouterr().err
    db = cantools.database.load_file("case1.dbc")
    assert db.get_message_by_name("BRAKE_CMD_C6").frame_id == 0x086
    assert main(["analyze", BUILTIN, "--ticks", "0"]) == 0, capsys.readouterr().err
    assert "SYNC" in capsys.readouterr().out
    assert main(["sweep", BUILTIN, "--grid", "delay=0,1ms", "--duration", "0.005", "--workers", "0",
                 "--out", "sw", "--no-plots", "-q"]) == 0, capsys.readouterr().err
    assert len((tmp_path / "sw" / "results.csv").read_text().splitlines()) == 3  # header + 2 points


def test_overrides_are_named_as_the_user_gave_them():
    """A bad value given as a keyword argument of the API names the keyword, not `--set`."""
    import canbrake
    from canbrake.scenario import ScenarioError

    with pytest.raises(ScenarioError, match=r"^keyword argument duration_s: Input should be greater than 0$"):
        canbrake.load_scenario(BUILTIN, duration_s=-1)
    with pytest.raises(ScenarioError, match=r"^keyword argument initial__speed_kmh__9: '9' is not an index"):
        canbrake.load_scenario(BUILTIN, initial__speed_kmh__9=3.0)
    with pytest.raises(ScenarioError, match=r"^keyword argument log_format: Input should be 'log'"):
        canbrake.run(BUILTIN, bus="inprocess", log_format="csv")
    with pytest.raises(ScenarioError, match=r"^keyword argument controller__params__k: Input should be a valid number"):
        canbrake.run(BUILTIN, bus="inprocess", controller__params__k="x")


# ----------------------------------------------------------------------------- reports from an installed package
_REPORT_LOOKUPS = """
import sys
from pathlib import Path
import canbrake
assert Path(canbrake.__file__).resolve().is_relative_to(Path(sys.argv[1]).resolve()), canbrake.__file__
from canbrake.scenario import load_scenario
from canbrake.report import (REPORTS, cai2014, chen2023, delay, ecp, ecp_literature, hh_consensus, li2024, mixed_emu,
                             safety)
assert sorted(REPORTS) == ["cai2014", "chen2023", "delay", "ecp", "ecp_literature", "hh_consensus", "li2024",
                           "mixed_emu", "safety"], REPORTS  # all looked up below
for spec in chen2023.run_specs():
    chen2023.resolve_spec(spec)
for spec in cai2014.run_specs():
    cai2014.resolve_spec(spec)
sd = li2024.scenario_dir()
for spec in li2024.run_specs():
    li2024._load(spec.scenario, spec.profile, spec.overrides(10.0), sd)
li2024.train_of(sd).load_route(sd)
for spec in ecp.SPECS:
    ecp._load(spec, 10.0, ecp.scenario_dir())
for case in ecp_literature.CASES:
    for spec in case.specs():
        ecp._load(spec, 10.0, ecp.scenario_dir())
load_scenario(delay.scenario_path())
for case in mixed_emu.CASES:
    mixed_emu._load(case, None)
for case in hh_consensus.CASES:
    hh_consensus._load(case, None)
load_scenario(safety.BASE)
print("found")
"""


def test_every_report_finds_its_scenarios_from_an_installed_package(tmp_path):
    """`pip install .` puts the built-in scenarios inside the package (canbrake/scenarios); the
    reports looked for them beside it (site-packages/scenarios) or in the working directory.
    The package is copied alone (its scenarios link followed, as the wheel does) and each
    report's scenario lookup runs from an empty directory."""
    site = tmp_path / "site"
    shutil.copytree(ROOT / "canbrake", site / "canbrake", ignore=shutil.ignore_patterns("__pycache__"))
    assert not (site / "scenarios").exists() and (site / "canbrake" / "scenarios" / CASE1.name).is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    r = subprocess.run([sys.executable, "-c", _REPORT_LOOKUPS, str(site)], cwd=empty, capture_output=True,
                       text=True, timeout=300, env={**__import__("os").environ, "PYTHONPATH": str(site)})
    assert r.returncode == 0 and r.stdout.strip() == "found", r.stderr[-2000:]
