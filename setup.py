"""Build of pd-service: the package is pure Python; the modules of the daemon's per-message
path are also compiled to C extensions with mypyc (part of mypy) when a C compiler is there.

The compiled modules are the same source: Python imports the extension in place of the .py
file. Beside them, small C kernels (``pd_service.native.C_KERNELS``: the Kalman arithmetic of
the linear backend) are built too, all or nothing with the modules; their numpy forms stay
the reference. Without a compiler (or with ``PD_SERVICE_PURE=1`` at install time) the package
installs as pure Python and behaves the same, only slower; ``PD_SERVICE_PURE=1`` at run time
also makes an installed compiled package use its .py files. The list of modules is
``pd_service.native.HOT_MODULES``.
Measured gain: docs/service.md, "Compiled hot path".
"""

from __future__ import annotations

import importlib.util
import os
import sys
import sysconfig
from pathlib import Path

from setuptools import setup
from setuptools.command.build_ext import build_ext


def _native():  # pd_service/native.py, read without importing the package
    spec = importlib.util.spec_from_file_location("_pd_native", "pd_service/native.py")
    assert spec is not None and spec.loader is not None
    native = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(native)
    return native


def _hot_files() -> list[str]:
    """The files of pd_service.native.HOT_MODULES."""
    native = _native()
    return [os.path.relpath(native.source_path(m)) for m in native.HOT_MODULES]


def _ext_modules() -> list:
    if os.environ.get("PD_SERVICE_PURE") == "1":
        print("pd-service: PD_SERVICE_PURE=1, installing pure Python", file=sys.stderr)
        return []
    try:
        import numpy
        from mypyc.build import mypycify
        from setuptools import Extension

        # mypyc.ini: the types `make lint` checks, from numpy's and pydantic's own stubs
        exts = mypycify(["--config-file", "mypyc.ini", *_hot_files()],
                        group_name="pd_service.native", opt_level="3")
        # the C kernels (pd_service.native.C_KERNELS), on numpy's C API (numpy is a build
        # requirement; an extension built against numpy 2 also runs with numpy 1.26)
        return exts + [Extension(name, [src], include_dirs=[numpy.get_include()],
                                 extra_compile_args=["-O2"])
                       for name, src in _native().C_KERNELS.items()]
    except (Exception, SystemExit) as exc:  # mypyc missing or refusing: pure Python
        print(f"pd-service: not compiling the hot path ({type(exc).__name__}: {exc}); "
              "installing pure Python", file=sys.stderr)
        return []


class OptionalBuildExt(build_ext):
    """build_ext that falls back to pure Python when compiling fails (no C compiler, no
    Python headers): all of the compiled modules or none (a module's extension needs the
    shared library of the group). Only a build that succeeded writes the digest of the
    sources it was made from (pd_service/native.sha256, in the source tree and the built
    package): pd_service.native runs the extensions only when it matches the .py files."""

    def run(self) -> None:
        if not self.extensions:
            return
        native = _native()
        digests = [native.DIGEST_FILE, Path(self.build_lib, "pd_service", "native.sha256")]
        for path in digests:  # no digest while building: a failure leaves none
            path.unlink(missing_ok=True)
        try:
            super().run()
        except Exception as exc:
            suffix = sysconfig.get_config_var("EXT_SUFFIX")
            for ext in self.extensions:  # built here, or left in place by an older build
                for path in (Path(self.get_ext_fullpath(ext.name)),
                             Path(*ext.name.split(".")).with_suffix(suffix)):
                    path.unlink(missing_ok=True)
            print(f"pd-service: compiling the hot path failed ({type(exc).__name__}: {exc}); "
                  "installing pure Python", file=sys.stderr)
            return
        digest = native.sources_digest() + "\n"
        for path in digests:
            if path.parent.is_dir():
                path.write_text(digest)


setup(ext_modules=_ext_modules(), cmdclass={"build_ext": OptionalBuildExt})
