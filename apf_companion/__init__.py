"""apf-companion: bacteria-point artificial-potential-field path planning for MAVLink drones.

Planners follow Diab, Mohammadkarimi, Rajan, "Artificial Potential Field-Based Path Planning for
Cluttered Environments", IEEE Aerospace 2023 (DOI 10.1109/AERO55745.2023.10115857).
"""

from __future__ import annotations

import logging

__all__ = ["__version__"]
__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
