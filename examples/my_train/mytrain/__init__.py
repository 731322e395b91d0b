"""An example of a user's own canbrake controller package (see docs/your-own-train.md)."""
