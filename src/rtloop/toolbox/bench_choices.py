"""What ``rtloop bench`` offers: the experiments and the stress-ng stressor groups.

Names only, apart from :mod:`rtloop.toolbox.bench` (the runs, with numpy and the app
description): the command line imports this module to build its arguments, and
``rtloop --help`` never loads an engine.
"""

EXPERIMENTS = ("affinity", "stress", "cyclictest")
STRESSORS = {
    "cpu": ["--cpu", "1"],
    "vm": ["--vm", "1", "--vm-bytes", "128M"],
    "io": ["--io", "1"],
    "cache": ["--cache", "1"],
}
"""stress-ng stressor groups (``--stress`` picks some; each gets one worker on the task's core)."""
DEFAULT_STRESS = ("cpu", "vm", "io")
