"""Applications built on the engine, not part of it: the bench's experiments, parameter sweeps, the
systemd unit of ``rtloop service`` and the runs it keeps, what ``rtloop top`` reads, and the
doctor's checks. Each is reached through its command in :mod:`rtloop.cli` (and ``rtloop.sweep``);
the engine (:mod:`rtloop.runtime`) never imports them.

Named ``toolbox`` rather than ``tools``: the checkout's top-level ``tools/`` holds the scripts
that set up a machine (the aarch64 and RT-kernel guests), not importable code.
"""
