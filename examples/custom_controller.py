"""Run your own controller: in a module (my_controller.py here) it runs on every bus, with one
OS process per ECU; defined in the script or notebook itself, use bus="inprocess" or "virtual".

    python examples/custom_controller.py
"""
import canbrake
from canbrake.control.base import ControlOutput, Controller, register

import my_controller  # noqa: F401  (registers "my_pd")

r = canbrake.run("chen2023_case1_fine_rail", duration_s=0.2, controller__name="my_pd",
                 controller__params={"kp": 20.0, "kc": 5.0}, plots=False)
print("my_pd on the in-memory bus:", r)


@register("brake_hard")
class BrakeHard(Controller):
    """Every car brakes at a fixed deceleration decel_mps2 (m/s^2), whatever the reference."""

    def __init__(self, car_index, n_cars, mass_kg, dt_s, *, decel_mps2: float = 1.0):
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        self.decel_mps2 = decel_mps2

    def step(self, obs):
        return ControlOutput(brake_force_n=self.mass_kg * self.decel_mps2)


r2 = canbrake.run("chen2023_case1_fine_rail", bus="inprocess", duration_s=0.2, controller__name="brake_hard",
                  controller__params={"decel_mps2": 1.0}, plots=False)
print("brake_hard in process:", r2)
