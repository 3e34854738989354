"""Tools touching a model: the probe, the grasp, patch contact with friction, haptic loops and
devices."""
