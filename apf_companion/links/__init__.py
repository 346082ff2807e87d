"""apf_companion.links."""
