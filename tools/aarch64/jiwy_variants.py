"""Simulate JIWY with each kind of plant and keep the signals, for a comparison across CPUs.

    python tools/aarch64/jiwy_variants.py OUT_DIR [--duration S]

Writes OUT_DIR/<variant>/signals.csv (and the rest of `rtloop simulate`'s artifacts) for:
  python   examples/jiwy/jiwy.toml as it is (Python plant and controller)
  20sim    the same app, the plant being the 20-sim-shaped C++ export (examples/jiwy/models/Plant)
  fmu      the same app, the plant being an FMU built here from examples/jiwy/models/fmu
Each runs `rtloop simulate --feed setpoint=examples/jiwy/setpoints/step.csv`, so the loop
moves (without a setpoint every signal stays 0). Run from the root of a checkout.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

EXAMPLE = Path("examples/jiwy")
PLANT_RUNNABLE = 'runnable = "jiwy_models:JiwyPlant"'


def _app_with_plant(model: str | None, work: Path) -> Path:
    """A copy of the JIWY example whose plant is ``model`` (None: as it is)."""
    copy = work / "jiwy"
    text = (EXAMPLE / "jiwy.toml").read_text()
    if model is not None:
        if text.count(PLANT_RUNNABLE) != 1:
            raise SystemExit(f"{EXAMPLE / 'jiwy.toml'}: expected one line {PLANT_RUNNABLE!r} to replace")
        text = text.replace(PLANT_RUNNABLE, f'model = "{model}"')
    app = copy / f"jiwy-{(model or 'python').split(':')[0]}.toml"
    app.write_text(text)
    return app


def _simulate(app: Path, out: Path, duration_s: float) -> None:
    command = [
        sys.executable, "-m", "rtloop.cli", "simulate", str(app), "--duration", str(duration_s),
        "--out", str(out), "--feed", f"setpoint={EXAMPLE / 'setpoints' / 'step.csv'}", "--quiet",
    ]  # fmt: skip
    print("+", " ".join(command), flush=True)
    subprocess.run(command, check=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--duration", type=float, default=2.0, metavar="S")
    args = parser.parse_args()
    from rtloop.models.fmu_build import build_fmu

    with tempfile.TemporaryDirectory(prefix="rtloop-jiwy-variants-") as tmp:
        work = Path(tmp)
        shutil.copytree(EXAMPLE, work / "jiwy")
        fmu = build_fmu(EXAMPLE / "models" / "fmu", work / "jiwy" / "JiwyPlant.fmu")
        variants = {
            "python": None,
            "20sim": "20sim:models/Plant",
            "fmu": f"fmu:{fmu.name}",
        }
        for name, model in variants.items():
            app = _app_with_plant(model, work)
            _simulate(app, args.out / name, args.duration)
    return 0


if __name__ == "__main__":
    sys.exit(main())
