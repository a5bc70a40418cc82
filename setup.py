"""Builds the optional C hot path (and the devices' per-cycle work in C); everything else is in pyproject.toml.

``optional=True``: without a compiler the build only warns and rtloop runs its
pure-Python path (and says so once at run time).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "rtloop.ipc._hotpath",
            sources=["src/rtloop/ipc/_hotpath.c"],
            depends=["src/rtloop/ipc/_schema.h"],
            extra_compile_args=["-O2", "-Wall", "-Wextra", "-Wno-unused-parameter", "-Wno-missing-field-initializers"],
            optional=True,
        ),
        Extension(
            "rtloop.io._devio",
            sources=["src/rtloop/io/_devio.c"],
            extra_compile_args=["-O2", "-Wall", "-Wextra", "-Wno-unused-parameter", "-Wno-missing-field-initializers"],
            optional=True,
        ),
    ],
)
