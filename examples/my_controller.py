"""A user's controller in its own module, so that every ECU process can import it.

A controller is one class with explicit state and no I/O (canbrake.control.base.Controller);
@register makes it available to scenarios as controller.name: my_pd.
"""
from canbrake.control.base import ControlOutput, Controller, Observation, register


@register("my_pd")
class MyPD(Controller):
    """Brake force F = m (a* + kp (v - v*) + kc (v - v_ahead)) in N (+ brakes); kp, kc in 1/s.

    v_ahead is the speed of the car in front as received over CAN (its own speed for car 1)."""

    diagnostic_names = ("speed_error_mps",)

    def __init__(self, car_index: int, n_cars: int, mass_kg: float, dt_s: float, *,
                 kp: float = 20.0, kc: float = 5.0) -> None:
        super().__init__(car_index, n_cars, mass_kg, dt_s)
        self.kp, self.kc = float(kp), float(kc)

    def step(self, obs: Observation) -> ControlOutput:
        e = obs.speed_mps - obs.ref_speed_mps
        ahead = obs.peer_speed_mps[self.car_index - 1] if self.car_index > 0 else obs.speed_mps
        if ahead != ahead:  # NaN: nothing received from the car ahead yet
            ahead = obs.speed_mps
        force = self.mass_kg * (obs.ref_decel_mps2 + self.kp * e + self.kc * (obs.speed_mps - ahead))
        return ControlOutput(brake_force_n=force, diagnostics={"speed_error_mps": e})
