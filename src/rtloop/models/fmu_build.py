"""Build a small co-simulation FMU from C sources (tests, examples, benchmarks).

Layout of ``src_dir``: ``modelDescription.xml`` and ``sources/*.c``. The sources are
compiled with ``gcc -O2 -ffp-contract=off -fPIC -shared`` (no fused multiply-add, so
the same bits on x86-64 and aarch64) into
``binaries/<platform>/<modelIdentifier>.so`` (FMI 2: ``linux64``; FMI 3:
``x86_64-linux`` / ``aarch64-linux``) and zipped with the description and the sources.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

from rtloop.models.base import ModelBuildError, ModelError

__all__ = ["build_fmu"]


def _platform_dir(fmi_version: str) -> str:
    from fmpy import platform, platform_tuple

    folder: str = platform_tuple if fmi_version.startswith("3") else platform
    return folder


def build_fmu(src_dir: str | os.PathLike[str], out_path: str | os.PathLike[str]) -> Path:
    """Compile ``src_dir/sources/*.c`` and zip an FMU at ``out_path``; return its path.

    Raises :class:`~rtloop.models.base.ModelBuildError` with the compiler's output.
    """
    src = Path(src_dir).resolve()
    out = Path(out_path).resolve()
    description = src / "modelDescription.xml"
    root = ET.parse(description).getroot()
    fmi_version = root.get("fmiVersion", "")
    identifiers = {
        element.get("modelIdentifier")
        for element in root
        if element.tag in ("CoSimulation", "ModelExchange")
    }
    identifiers.discard(None)
    if len(identifiers) != 1:
        raise ModelError(f"{description}: expected one modelIdentifier, found {identifiers}")
    identifier = identifiers.pop()
    compiler = shutil.which(os.environ.get("CC", "gcc"))
    if compiler is None:
        raise ModelError("cannot build an FMU: gcc not found (apt install build-essential)")
    sources = sorted((src / "sources").glob("*.c"))

    with tempfile.TemporaryDirectory(prefix="rtloop-fmu-") as tmp:
        binary = Path(tmp) / "binaries" / _platform_dir(fmi_version) / f"{identifier}.so"
        binary.parent.mkdir(parents=True)
        command = [
            compiler, "-O2", "-ffp-contract=off", "-fPIC", "-shared", "-fvisibility=hidden",
            f"-I{src / 'sources'}", *map(str, sources), "-o", str(binary), "-lm",
        ]  # fmt: skip
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            raise ModelBuildError(str(src), command, done.stdout + done.stderr)
        out.parent.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as fmu:
            fmu.write(description, "modelDescription.xml")
            fmu.write(binary, binary.relative_to(tmp).as_posix())
            for p in sorted((src / "sources").iterdir()):
                fmu.write(p, f"sources/{p.name}")
    return out
