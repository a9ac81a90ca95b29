"""Storage of telemetry, estimates, warnings, credentials and estimator states: SQLite or PostgreSQL (SQLAlchemy)."""
