"""Shared memory between processes; here, for now, the per-cycle hot path (C and Python)."""
