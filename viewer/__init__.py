"""moderngl preview of a rig driven by solved weights (draws only)."""
