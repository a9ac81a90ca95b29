"""After storage: the friction map, the warnings, roadside stations, and what is published."""
