"""A small sweep: frame delay x loss on every ECU's frames, one seed, 0.1 s each, in this process.

    python examples/sweep_delay.py
"""
import canbrake

df = canbrake.sweep("chen2023_case1_fine_rail", {"delay": [0.0, 0.005], "loss": [0.0, 0.2]},
                    duration_s=0.1, seeds=1)
print(df[["delay_s", "loss", "status", "max_abs_deflection_m", "speed_rmse_kmh_max", "safety"]].to_string())
print("heatmaps and results.csv in", df.attrs["out"])
