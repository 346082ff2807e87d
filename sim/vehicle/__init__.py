"""sim.vehicle."""
