"""``rtloop bench``: the thesis's chapter-6 experiments (section 6.3) on this machine.

    rtloop bench affinity   --duration 10 --out runs/bench-affinity
    rtloop bench stress     --duration 10 --out runs/bench-stress
    rtloop bench cyclictest --duration 10 --out runs/bench-cyclictest
    rtloop bench all        --duration 10 --out runs/bench

- ``affinity``: two tasks finding the primes up to 700 at 1 kHz, priorities 80 and 79,
  on the same core (``same-core``) and on different cores (``different-cores``).
- ``stress``: one task alone on its core (``quiet``) and with ``stress-ng`` load pinned
  to that core (``stressed``).
- ``cyclictest``: a no-op task and ``cyclictest`` with the same priority, core and period,
  one after the other.

Each run is an ordinary run directory (``summary.json``, ``timing.csv``, ...); each
experiment also writes a comparison ``report.html`` and ``table.md`` into its directory
and prints the table. A machine that cannot run an experiment as asked (no real-time
privilege, stress-ng or cyclictest missing, one CPU) is refused with the reason, exit 2.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rtloop.cli.arguments import count, positive_seconds
from rtloop.stats import DEFAULT_TRIM
from rtloop.toolbox.bench_choices import DEFAULT_STRESS, EXPERIMENTS, STRESSORS  # the runs import lazily

if TYPE_CHECKING:
    from rtloop.toolbox.bench import Outcome, Settings

HELP = "the thesis's chapter-6 experiments on this machine, with a report"


def _write_report(run_dirs: list[Path], out: Path) -> Path | None:
    """The comparison report.html of an experiment's runs."""
    from rtloop.report.build import build_report

    return build_report(run_dirs, out=out).html


# --- command line --------------------------------------------------------------------------------
def _stressors(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in STRESSORS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a comma-separated list of {', '.join(STRESSORS)}")
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (__doc__ or "").replace("``", "")
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("experiment", choices=(*EXPERIMENTS, "all"), help="which experiment (all: the three)")
    parser.add_argument("--duration", type=positive_seconds, default=10.0, metavar="S",
                        help="seconds per run (default 10)")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="output directory (default runs/bench-EXPERIMENT; with all, one subdirectory each)")
    parser.add_argument("--cpu", type=int, metavar="N", help="the measured core (default: the highest one)")
    parser.add_argument("--stress", type=_stressors, default=DEFAULT_STRESS, metavar="LIST",
                        help=f"stress-ng stressors for stress, from {','.join(STRESSORS)} "
                             f"(default {','.join(DEFAULT_STRESS)})")
    parser.add_argument("--stress-task", choices=("primes", "noop"), default="primes",
                        help="the task measured under stress (default primes)")
    parser.add_argument("--trim", type=count, default=DEFAULT_TRIM, metavar="N",
                        help=f"cycles left out at each end of the statistics (default {DEFAULT_TRIM})")
    parser.add_argument("--allow-non-rt", action="store_true",
                        help="run under SCHED_OTHER where real-time scheduling is not allowed (numbers mean little)")


def settings_for(args: argparse.Namespace, experiment: str, policy: str, cpus: tuple[int, int]) -> Settings:
    from rtloop.toolbox.bench import Settings

    if args.experiment == "all":
        out = (args.out or Path("runs/bench")) / experiment
    else:
        out = args.out or Path(f"runs/bench-{experiment}")
    return Settings(args.duration, out, cpus[0], cpus[1], policy, args.stress, args.stress_task, args.trim,
                    write_report=_write_report)


def run_experiments(args: argparse.Namespace) -> list[Outcome]:
    """Check the machine, then run each asked experiment in turn, with progress on stderr."""
    from rtloop.toolbox.bench import RUNNERS, RUNS_PER_EXPERIMENT, check_tools, choose_cpus, choose_policy, progress

    experiments = EXPERIMENTS if args.experiment == "all" else (args.experiment,)
    check_tools(experiments)
    cpus = choose_cpus(args.cpu)
    policy = choose_policy(args.allow_non_rt)
    runs = sum(RUNS_PER_EXPERIMENT[e] for e in experiments)
    progress(f"{len(experiments)} experiment(s), {runs} runs of {args.duration:g} s (≈{runs * (args.duration + 2):.0f}"
             f" s with start-up and reports); measured cpu {cpus[0]}, other cpu {cpus[1]}, {policy}")
    outcomes = []
    for index, experiment in enumerate(experiments, start=1):
        settings = settings_for(args, experiment, policy, cpus)
        progress(f"[{index}/{len(experiments)}] {experiment} → {settings.out}")
        started = time.monotonic()
        outcome = RUNNERS[experiment](settings)
        progress(f"[{index}/{len(experiments)}] {experiment}: {time.monotonic() - started:.1f} s, "
                 f"report {outcome.report}")
        print(outcome.markdown() + "\n", flush=True)
        outcomes.append(outcome)
    return outcomes


def run(args: argparse.Namespace) -> int:
    """0 when every experiment ran; a machine that cannot run them as asked is bad input (exit 2, saying why)."""
    run_experiments(args)
    return 0
