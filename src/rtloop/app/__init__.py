"""What runs: the description of an app (builder, signal references, app files). Knows nothing of running."""
