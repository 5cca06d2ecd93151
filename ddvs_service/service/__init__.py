"""The servo service: a headless Zenoh node turning camera frames into camera twists (`ddvs serve`)."""
