"""apf_companion.planning."""
