"""canbrake: CAN-bus-in-the-loop emulator for distributed train braking control."""

__version__ = "0.1.0"
