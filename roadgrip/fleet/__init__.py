"""Vehicles that talk to the cloud: simulated terminals and replays of recorded logs."""
