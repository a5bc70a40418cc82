"""JIWY in Python: the thesis's listing C.1 written with rtloop's App builder.

    sudo python examples/jiwy/main.py --duration 10 --out runs/jiwy-py

Same app as jiwy.toml: controller and plant at 1 kHz, wired both ways, setpoints
through a port (a step at t = 0.5 s here), angles recorded.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jiwy_models import JiwyController, JiwyPlant

import rtloop
from rtloop import App
from rtloop.cli.run import format_summary

HERE = Path(__file__).parent
PERIOD_NS = 1_000_000  # 1 kHz, as in the thesis


def build_app(setpoints: Path | None = HERE / "setpoints" / "step.csv", cpu: int | None = 1) -> App:
    app = App("jiwy")
    controller = app.add_task("controller", JiwyController(), period_ns=PERIOD_NS, priority=80, cpu=cpu)
    plant = app.add_task("plant", JiwyPlant(), period_ns=PERIOD_NS, priority=81, cpu=cpu)
    app.connect(plant.y[0:2], controller.u[0:2])  # measured angles
    app.connect(controller.y[0:2], plant.u[0:2])  # steering
    app.port("setpoint", to=controller.u[2:4], feed=setpoints)
    app.port("angles", source=plant.y[0:2])
    app.record(plant.y, controller.y, controller.u[2:4])
    return app


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=Path("runs/jiwy-py"))
    parser.add_argument("--simulate", action="store_true", help="offline, lock-step, no RT needed")
    args = parser.parse_args()
    app = build_app()
    run = rtloop.simulate if args.simulate else rtloop.run
    summary = run(app, args.duration, args.out)
    print(format_summary(summary, args.out))


if __name__ == "__main__":
    main()
