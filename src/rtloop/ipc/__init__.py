"""Shared memory between processes: segments, channels, status words, the ports client."""
