"""The onboard flight service: config, flight state machine, loops and process (one per drone)."""
