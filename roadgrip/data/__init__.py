"""Telemetry schema (the one source of truth for columns and units) and dataset I/O."""
