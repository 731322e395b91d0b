"""``my_speed_pi``: each car tracks v* with a PI loop and eases its brake force by the coupler
deflection it measures (a user's own controller, found by canbrake through the entry point
``canbrake.controllers`` of this package's pyproject.toml).

    F_i = m_i (a* + kp (v_i − v*) + ki ∫(v_i − v*) dt) + k_defl (Δl_front − Δl_rear)    (N, + brakes)

Pure: no I/O, explicit state, SI units. The ECU calls :meth:`step` once per control period.
"""
from __future__ import annotations

from canbrake.control.base import ControlOutput, Controller, Observation


class MySpeedPI(Controller):
    """Parameters: ``kp`` (1/s), ``ki`` (1/s²), ``k_defl_n_per_m`` (N/m), ``max_decel_mps2`` (m/s²)."""

    diagnostic_names = ("speed_error_mps",)
    # what this ECU reads from its car's sensors and what it sends to the brake unit / its peers
    sensor_names = ("speed_mps", "position_m", "deflection_front_m", "deflection_rear_m")
    command_names = ("brake_force_n",)
    broadcast_names = ("speed_mps",)

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *, kp: float = 1.5,
                 ki: float = 0.3, k_defl_n_per_m: float = 0.0, max_decel_mps2: float = 1.4) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        if kp < 0 or ki < 0 or max_decel_mps2 <= 0:
            raise ValueError("kp and ki must be >= 0 and max_decel_mps2 > 0")
        self.kp, self.ki, self.k_defl, self.max_decel = kp, ki, k_defl_n_per_m, max_decel_mps2
        self.integral_m = 0.0

    def step(self, obs: Observation) -> ControlOutput:
        e = obs.speed_mps - obs.ref_speed_mps
        self.integral_m += e * self.dt_s
        front = obs.sensors.get("deflection_front_m", 0.0)
        rear = obs.sensors.get("deflection_rear_m", 0.0)
        force = self.mass_kg * (obs.ref_decel_mps2 + self.kp * e + self.ki * self.integral_m)
        force += self.k_defl * (front - rear)
        limit = self.max_decel * self.mass_kg
        force = max(-limit, min(limit, force))
        return ControlOutput(force, {"speed_error_mps": e})
