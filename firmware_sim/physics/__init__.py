"""Physics of the simulated world: Earth, platform, table, sensors."""
