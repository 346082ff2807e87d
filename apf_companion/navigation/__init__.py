"""The parts of the navigator (``apf_companion.navigator.Navigator`` is the facade the service uses): each module
owns one piece of its state. Pure and clock-injected, as the navigator."""
