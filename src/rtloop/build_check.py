"""Is a compiled extension the build of the C sources beside it? (the hot path's and the devices')

``setup.py`` passes each extension the digest of the sources it compiles (``SOURCES_DIGEST``); here
the same digest is taken of the files there now. A build older than its sources (a checkout changed
after ``pip install -e .``) would call its objects with arguments they no longer take or compute
what the Python reference no longer does: the caller then runs the Python twin and says why. An
installed wheel ships no C sources: it was built in one go from its own, and is believed.
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any


def sources_digest(folder: Path, names: list[str]) -> str | None:
    """CRC-32 of each file's relative name and bytes, in order (what setup.py computes); None when a
    file is missing (no sources shipped). CRC-32 tells a changed file, and a task process has zlib
    already (hashlib would load OpenSSL into every task)."""
    digest = 0
    for name in names:
        try:
            digest = zlib.crc32(name.encode() + b"\0" + (folder / name).read_bytes() + b"\0", digest)
        except FileNotFoundError:
            return None
    return f"{digest:08x}"


def stale_build(module: Any, what: str, here: str | None, sources: str) -> str:
    """Why ``module`` is not the build of the sources whose digest is ``here`` ("" when it is, or cannot
    be told: no sources); ``sources`` names them for the message."""
    if here is None:
        return ""
    built = getattr(module, "SOURCES_DIGEST", None)
    if not built:
        return f"{what} was built without its sources' digest (an older build): rebuild it (pip install -e .)"
    if built != here:
        return f"{what} was built from other sources than {sources} hold now: rebuild it (pip install -e .)"
    return ""
