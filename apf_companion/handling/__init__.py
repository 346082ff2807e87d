"""The parts of the autopilot handlers (``apf_companion.handlers.AutopilotHandlers`` is the dispatcher the service
uses): each module owns one piece of what the autopilot's records carry, or owns nothing and hands them on."""
