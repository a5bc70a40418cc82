"""Writers of a run's artifacts (timing.csv, signals.csv, run.mcap)."""
