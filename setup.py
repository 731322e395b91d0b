"""Build of canbrake's compiled core: every ``canbrake/**/*.pyx`` is a Cython extension.

Everything else (metadata, dependencies, entry points) is in pyproject.toml. The extensions are
also copied next to their sources (as setuptools' ``build_ext --inplace`` does, after the normal
build, so the wheel holds them too): the README's test command, ``python -m pytest``, imports
canbrake from the checkout, which must therefore hold the compiled modules it was installed with.
"""
from __future__ import annotations

from pathlib import Path

from setuptools import setup
from setuptools.command.build_ext import build_ext

HERE = Path(__file__).resolve().parent
NO_COMPILER = ("canbrake: could not build its compiled core ({}); it needs a C compiler and the Python "
               "headers: install them (Debian/Ubuntu: apt install gcc python3-dev) and retry")


class BuildExt(build_ext):
    """build_ext that says in one line what is missing when there is no working C compiler."""

    def run(self) -> None:
        try:
            super().run()
            # next to the sources too (see the module docstring); the build dir keeps its copy
            # for the wheel
            self.copy_extensions_to_source()
        except Exception as exc:  # the compiler errors' classes differ between setuptools releases
            raise SystemExit(NO_COMPILER.format(str(exc).strip() or type(exc).__name__)) from None


def extensions() -> list:
    from Cython.Build import cythonize
    from setuptools import Extension

    exts = []
    for pyx in sorted(HERE.glob("canbrake/**/*.pyx")):
        rel = pyx.relative_to(HERE)
        name = ".".join(rel.with_suffix("").parts)
        exts.append(Extension(name, [str(rel)], extra_compile_args=["-O2"]))
    return cythonize(exts, language_level=3, quiet=True,
                     compiler_directives={"boundscheck": False, "wraparound": False, "cdivision": True})


setup(ext_modules=extensions(), cmdclass={"build_ext": BuildExt})
