"""apf_companion.perception."""
