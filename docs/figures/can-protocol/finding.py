"""Regenerate the finding of docs/can-protocol.md: one ECU drifts into bus-off and recovers,
with and without the fail-safe reaction of the brake units.

    python docs/figures/can-protocol/finding.py [RUNS_DIR]

Runs Chen 2023 case 1, realistic profile (10 ms, 1 Mbit/s, 0.3 s brake lag), all cars at
90 km/h, lockstep with the CAN timing model, in-process; writes table.md and finding.png next to
this file (run directories under RUNS_DIR, default runs/can-protocol).
"""
from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
FAULT = {"type": "faulty_transceiver", "node": "ecu3", "probability": 0.6, "start_s": 2.0, "stop_s": 5.0,
         "recovery_delay_s": 0.2}
VARIANTS = {
    "no bus errors": {},
    "ecu3 bus-off, no fail-safe": {"bus.impairments": [FAULT]},
    "ecu3 bus-off, fail-safe (released by the next command)": {
        "bus.impairments": [FAULT], "safety.command_timeout_s": 0.1, "safety.latch": False},
    "ecu3 bus-off, fail-safe (latched)": {
        "bus.impairments": [FAULT], "safety.command_timeout_s": 0.1, "safety.latch": True},
}


def main(runs: Path) -> None:
    sys.path.insert(0, str(ROOT))  # this checkout's canbrake
    from canbrake.run import run_scenario
    from canbrake.scenario import load_scenario

    rows, traces = [], {}
    for i, (label, over) in enumerate(VARIANTS.items()):
        o = {"initial.speed_kmh": 90, "mode": "lockstep", "bus.timing": "model", **over}  # like --set
        scn = load_scenario(ROOT / "scenarios" / "chen2023_case1_fine_rail.yaml", profile="realistic", overrides=o)
        out = runs / f"v{i}"
        s = run_scenario(scn, out, backend="inprocess", plots=(i == 2))
        m = s["metrics"]
        e = (s.get("can_errors") or {}).get("nodes", {}).get("ecu3", {})
        fs = s.get("failsafe") or {}
        rows.append([label, f"{m['max_abs_deflection_m'] * 100:.2f}", f"{m['max_abs_coupler_force_n'] / 1000:.2f}",
                     f"{m['speed_max_abs_error_after_convergence_kmh']:.2f}",
                     f"{max(m['speed_rmse_after_convergence_kmh']):.3f}", f"{m['distance_excess_m']:.2f}",
                     f"{e.get('bus_off_episodes', 0)}", f"{e.get('bus_off_s', 0.0):.2f}",
                     f"{s['frames']['commands_missed']}", f"{s['frames']['peer_values_missing']}",
                     f"{fs.get('car_ticks', '-')}"])
        with open(out / "signals.csv") as f:
            cols = list(csv.DictReader(f))
        traces[label] = {k: np.array([float(r[k]) if r.get(k) not in ("", None) else np.nan for r in cols])
                         for k in ("t_s", "deflection_m_k2", "deflection_m_k4", "speed_mps_c3", "brake_applied_n_c3",
                                   "can_state_c3")
                         if k in cols[0]}
    head = ["variant", "max abs deflection (cm)", "max coupler force (kN)", "max speed error after conv. (km/h)",
            "speed RMSE after conv. (km/h, worst car)", "distance beyond reference (m)", "ecu3 bus-off episodes",
            "ecu3 bus-off time (s)", "commands missed", "peer values missing", "fail-safe car-ticks"]
    table = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]
    (HERE / "table.md").write_text("\n".join(table) + "\n")
    fig, axes = plt.subplots(4, 1, figsize=(9, 11), sharex=True)
    for i, (label, tr) in enumerate(traces.items()):
        t = tr["t_s"]
        axes[0].plot(t, tr["deflection_m_k4"] * 100, lw=1, color=f"C{i}", label=label)
        axes[1].plot(t, tr["deflection_m_k2"] * 100, lw=1, color=f"C{i}", label=label)
        axes[2].plot(t, tr["brake_applied_n_c3"] / 1000, lw=1, color=f"C{i}", label=label)
        if "can_state_c3" in tr:
            axes[3].step(t, tr["can_state_c3"] + 0.03 * i, where="post", lw=1, color=f"C{i}", label=label)
    axes[0].set(ylabel="coupler 4-5 deflection (cm)", title="car 3's ECU drifts into bus-off (2-5 s) and recovers")
    axes[1].set(ylabel="coupler 2-3 deflection (cm)")
    axes[2].set(ylabel="car 3 applied brake force (kN)")
    axes[3].set(ylabel="ecu3 CAN state", xlabel="time (s)", yticks=[0, 1, 2],
                yticklabels=["active", "passive", "bus-off"])
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(HERE / "finding.png", dpi=110)
    print("\n".join(table))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "runs" / "can-protocol")
