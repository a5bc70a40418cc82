"""Shared memory between processes: segments, channels, status words, the ports client,
and the per-cycle hot path (C, with its Python twin)."""
