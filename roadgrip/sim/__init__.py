"""The open vehicle simulator that replaces CarSim: roads, driver, sensors, integrator, scenarios and presets."""
