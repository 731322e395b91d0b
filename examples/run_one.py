"""Run one built-in scenario and read its results (no `if __name__ == "__main__":` needed).

    python examples/run_one.py
"""
import canbrake

# Chen et al.'s six-car metro braking from ~90 km/h, one OS process per ECU over the in-memory
# CAN bus; 0.2 s of simulated time instead of the scenario's 10 s to keep the example quick.
r = canbrake.run("chen2023_case1_fine_rail", duration_s=0.2)

print(r)                                    # status, max deflection, worst speed RMSE, run directory
print("verdict:", r.verdict)
m = r.summary["metrics"]
print(f"max |coupler deflection|: {m['max_abs_deflection_m'] * 100:.3f} cm")

sig = r.signals                              # pandas DataFrame indexed by simulated time t_s (s)
print(sig[["ref_speed_mps", "speed_mps_c1", "speed_mps_c6"]].iloc[::100])

n = sum(1 for f in r.frames() if f.arbitration_id == 0x083)   # BRAKE_CMD_C3 frames
print(f"BRAKE_CMD_C3 frames on the bus: {n}")
brake = r.decoded("BRAKE_CMD_C3")            # decoded with the run's own DBC (cantools)
print(brake[["Counter", "BrakeForce"]].head(3))
r.plot("overview").savefig(r.run_dir / "overview_again.png")
print("run directory:", r.run_dir)
