"""roadgrip: tire-road adhesion coefficient (mu) estimation from connected-vehicle telemetry."""

__version__ = "0.1.0"
