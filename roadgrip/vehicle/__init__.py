"""Vehicle parameters, tire models and the body dynamics of the simulator."""
