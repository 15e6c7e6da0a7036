"""Low-level motor skills: the tracking reward and task, experts, the expert library."""
