"""Plants that speak the ddvs protocol: the SAPIEN UR5 arm and the free-flying camera."""
