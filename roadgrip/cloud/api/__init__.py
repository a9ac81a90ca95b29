"""The HTTP API (FastAPI), the dashboard and the map exports."""
