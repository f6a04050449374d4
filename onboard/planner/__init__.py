"""Pure numerical core of the formation planner: no I/O, clocks or configuration files."""
