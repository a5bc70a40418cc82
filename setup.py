"""Builds the optional C hot path (and the devices' per-cycle work in C); everything else is in pyproject.toml.

``optional=True``: without a compiler the build only warns and rtloop runs its
pure-Python path (and says so once at run time).
"""

import zlib
from pathlib import Path

from setuptools import Extension, setup

HOTPATH_SOURCES = ["_hotpath.c", "_schema.h"]
DEVIO_SOURCES = sorted(["_devio.c", *(f"devio_c/{p.name}" for p in Path("src/rtloop/io/devio_c").glob("*.c"))])


def sources_digest(folder: Path, names: list[str]) -> str:
    """The digest rtloop/build_check.py computes the same way (the tests check they agree)."""
    digest = 0
    for name in names:
        digest = zlib.crc32(name.encode() + b"\0" + (folder / name).read_bytes() + b"\0", digest)
    return f"{digest:08x}"


setup(
    ext_modules=[
        Extension(
            "rtloop.ipc._hotpath",
            sources=["src/rtloop/ipc/_hotpath.c"],
            depends=["src/rtloop/ipc/_schema.h"],
            define_macros=[("RTLOOP_HOTPATH_SOURCES_DIGEST",
                            f'"{sources_digest(Path("src/rtloop/ipc"), HOTPATH_SOURCES)}"')],
            extra_compile_args=["-O2", "-Wall", "-Wextra", "-Wno-unused-parameter", "-Wno-missing-field-initializers"],
            optional=True,
        ),
        Extension(
            "rtloop.io._devio",
            sources=["src/rtloop/io/_devio.c"],  # it includes devio_c/*.c: one translation unit
            depends=[f"src/rtloop/io/{name}" for name in DEVIO_SOURCES],
            define_macros=[("RTLOOP_DEVIO_SOURCES_DIGEST",
                            f'"{sources_digest(Path("src/rtloop/io"), DEVIO_SOURCES)}"')],
            # -ffp-contract=off: no fused multiply-add (aarch64 has it), so the emulated drive's floats
            # (devio_c/esc_drive.c) are bit for bit its Python reference's
            extra_compile_args=["-O2", "-ffp-contract=off", "-Wall", "-Wextra", "-Wno-unused-parameter",
                                "-Wno-missing-field-initializers"],
            optional=True,
        ),
    ],
)
