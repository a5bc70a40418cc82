"""What grows in the supervisor during a soak: tracemalloc snapshots of ``rtloop.run`` over time.

    sudo .venv/bin/python benchmarks/bench_supervisor_memory.py --seconds 95

Runs a copy of examples/jiwy/jiwy.toml (its ROS 2 section left out, the step setpoint fed in,
``--keep 60`` as ``rtloop run`` without a duration uses) in this process, which is then the
supervisor, with tracemalloc on. ``on_progress`` (called at every drain, in the supervisor) takes a
snapshot at ``--first-s`` and at the end and reads VmRSS at each; the script prints the resident
growth and the allocation sites that grew most between the two snapshots (Python objects and
numpy buffers: numpy reports its allocations to tracemalloc).
"""

from __future__ import annotations

import argparse
import itertools
import os
import re
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
JIWY = ROOT / "examples" / "jiwy"


def rss_kib() -> dict[str, int]:
    """VmRSS and its parts (RssAnon: the heap; RssShmem: shared memory, here the run's segments)."""
    fields = ("VmRSS:", "RssAnon:", "RssFile:", "RssShmem:")
    return {line.split()[0][:-1]: int(line.split()[1]) for line in Path("/proc/self/status").read_text().splitlines()
            if line.startswith(fields)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=95.0)
    parser.add_argument("--first-s", type=float, default=15.0, help="the first snapshot (after start-up)")
    parser.add_argument("--keep", type=float, default=60.0)
    parser.add_argument("--top", type=int, default=15)
    parser.add_argument("--resident-only", action="store_true",
                        help="no tracemalloc (it adds its own memory): VmRSS alone, at the same times")
    args = parser.parse_args()

    sys.path.insert(0, str(JIWY))
    import rtloop
    from rtloop.app.appfile import load_app

    folder = Path(tempfile.mkdtemp(prefix="rtloop-memsoak-"))
    name = f"memsoak_{os.getpid()}"
    text = (JIWY / "jiwy.toml").read_text().split("# ROS 2 topics")[0]
    text = re.sub(r'^name = "jiwy"$', f'name = "{name}"', text, flags=re.M)
    app_file = folder / f"{name}.toml"
    app_file.write_text(text)
    app = load_app(app_file)
    app.feed("setpoint", JIWY / "setpoints" / "step.csv")

    if not args.resident_only:
        tracemalloc.start(8)
    marks = [args.first_s + (args.seconds - args.first_s - 5.0) * i / 2 for i in range(3)]  # since T0
    taken: list[tuple[float, tracemalloc.Snapshot, int]] = []
    t0: list[float] = []

    def on_progress(progress: object) -> None:
        now = time.monotonic()
        if not t0:
            t0.append(now)  # the first drain: the run has started
        if len(taken) < len(marks) and now - t0[0] >= marks[len(taken)]:
            snapshot = None if args.resident_only else tracemalloc.take_snapshot().filter_traces([
                tracemalloc.Filter(False, tracemalloc.__file__, all_frames=True),
                tracemalloc.Filter(False, __file__, all_frames=True)])  # not the snapshots' own memory
            taken.append((now - t0[0], snapshot, rss_kib()))

    rtloop.run(app, args.seconds, folder / "run", keep_s=args.keep, on_progress=on_progress)
    how = "" if args.resident_only else " (tracemalloc on: it adds its own)"
    print(f"supervisor resident memory{how}, MiB:")
    for at, _, kib in taken:
        print(f"  {at:4.0f} s after T0: " + ", ".join(f"{field} {value / 1024:.1f}" for field, value in kib.items()))
    for (at_a, a, _), (at_b, b, _) in itertools.pairwise(taken):
        if a is None or b is None:
            continue
        stats = b.compare_to(a, "traceback")
        total = sum(stat.size_diff for stat in stats)
        print(f"tracemalloc {at_a:.0f} s → {at_b:.0f} s after T0: {total / 1024:+.1f} KiB; the sites that grew most:")
        for stat in sorted(stats, key=lambda s: s.size_diff, reverse=True)[:args.top]:
            frames = [f"{Path(f.filename).name}:{f.lineno}" for f in stat.traceback]
            print(f"  {stat.size_diff / 1024:+9.1f} KiB {stat.count_diff:+7d} blocks  {' < '.join(frames[-4:])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
