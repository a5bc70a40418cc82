"""How an app runs: the supervisor, the real-time task loop, simulation, the run's shared-memory layout."""
