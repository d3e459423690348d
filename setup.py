"""Build of the compiled S_k kernel; everything else is declared in pyproject.toml."""

import sys

from setuptools import Extension, setup

extra = [] if sys.platform == "win32" else ["-O3", "-std=c11", "-Wall", "-Wextra"]

setup(
    ext_modules=[
        Extension(
            "stipi_daemon.analysis._skcount",
            sources=["stipi_daemon/analysis/_skcount.c"],
            extra_compile_args=extra,
            optional=True,
        )
    ]
)
