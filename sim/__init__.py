"""apf-sim: the bundled MAVLink vehicle simulator, obstacle worlds, and the paper's Monte Carlo study.

Uses apf_companion only through its public API; nothing in apf_companion imports sim.
"""
