"""Compare two controllers on the same scenario and seed (no `__main__` guard needed).

    python examples/run_and_compare.py

Chen et al.'s controller against a per-car PI speed controller with no communication, both
on the in-memory CAN bus with one OS process per ECU, 0.2 s of the fine-rail case.
"""
import canbrake

scenario = canbrake.load_scenario("chen2023_case1_fine_rail", duration_s=0.2)
# plots=False: no PNGs written (r.plot() still draws any of them on demand)
runs = {
    "chen2023 (consensus over CAN)": canbrake.run(scenario, plots=False),
    "pi (each car alone)": canbrake.run(scenario, controller__name="pi", controller__params={"kp": 36.0},
                                        plots=False),
}

print(f"{'controller':32} {'max |Δl| (cm)':>14} {'worst RMSE (km/h)':>18} {'frames':>7}")
for label, r in runs.items():
    m = r.summary["metrics"]
    print(f"{label:32} {m['max_abs_deflection_m'] * 100:14.3f} {max(m['speed_rmse_kmh']):18.3f} "
          f"{r.summary['frames']['on_bus']:7d}")

# the same comparison from the traces: the largest deflection of any coupler at any time
for label, r in runs.items():
    defl = r.signals.filter(regex=r"^deflection_m_k\d+$").abs().to_numpy().max()
    print(f"{label}: max |Δl| from signals = {defl * 100:.3f} cm")
