"""Visualisation with Foxglove: the service cycle live on a WebSocket and recorded to MCAP (docs/visualisation.md).

Needs the ``viz`` extra (foxglove-sdk). The service imports this package only when ``[visualisation]`` (or
``apf-companion run --foxglove / --mcap-dir``) asks for an output.
"""

from __future__ import annotations

from apf_companion.viz.frames import FRAME_ENU, FRAME_NED, NED_IN_ENU_XYZW, Topic, yaw_quaternion_xyzw

__all__ = ["FRAME_ENU", "FRAME_NED", "NED_IN_ENU_XYZW", "Topic", "yaw_quaternion_xyzw"]
