"""Choosing Mitsuba's variant deliberately, before it can pick a bad one itself.

Three backends matter here:

* ``cuda_ad_rgb`` on a machine with an NVIDIA GPU (fastest by far);
* ``llvm_ad_rgb`` on CPUs, 2-3x faster than scalar, but only with libLLVM 16 or
  newer. Dr.Jit loads whichever libLLVM it finds first, and the CPU images also
  carry mesa's LLVM 15, with which the first render aborts the whole process
  (SIGABRT, not catchable). So we look for a good library ourselves and point
  ``DRJIT_LIBLLVM_PATH`` at it *before* Dr.Jit is imported;
* ``scalar_rgb``, which always works.

``load_mitsuba(backend)`` returns the imported ``mitsuba`` module with the
variant set; everything in ``render`` gets Mitsuba through it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import re
import sys
from pathlib import Path
from types import ModuleType

from clothgap.errors import UserError

BACKENDS = ("auto", "cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
MIN_LLVM_VERSION = 16
LLVM_ENV = "DRJIT_LIBLLVM_PATH"

# Where distributions put libLLVM (Debian/Ubuntu multiarch, RHEL, Homebrew, conda).
_LLVM_DIRS = (
    "/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
    "/usr/local/lib", "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib",
)
_LLVM_NAME = re.compile(r"^libLLVM(?:-|\.so\.)(\d+)(?:[.\d]*)(?:\.so(?:[.\d]*)?|\.dylib)?$")


class BackendError(UserError, RuntimeError):
    """The requested Mitsuba backend cannot run on this machine; the message says why."""


def find_libllvm(min_version: int = MIN_LLVM_VERSION) -> Path | None:
    """The newest libLLVM of at least ``min_version`` in the usual library folders, or None.

    Matches ``libLLVM.so.19.1``, ``libLLVM-19.so`` and the ``/usr/lib/llvm-19/lib``
    layout; never returns mesa's LLVM 15 (or any older one).
    """
    candidates: list[tuple[int, Path]] = []
    dirs = [Path(d) for d in _LLVM_DIRS]
    dirs += sorted(Path("/usr/lib").glob("llvm-*/lib"))
    conda = os.environ.get("CONDA_PREFIX")
    if conda:
        dirs.append(Path(conda) / "lib")
    for folder in dirs:
        if not folder.is_dir():
            continue
        for path in folder.glob("libLLVM*"):
            match = _LLVM_NAME.match(path.name)
            if match and int(match.group(1)) >= min_version and path.is_file():
                candidates.append((int(match.group(1)), path))
    if not candidates:
        return None
    # Newest major first; among equals prefer the fully versioned file (a real library, not a linker stub).
    candidates.sort(key=lambda c: (c[0], len(c[1].name)), reverse=True)
    return candidates[0][1]


def cuda_device_count() -> int:
    """How many CUDA devices the driver reports (0 without a driver), without importing Dr.Jit."""
    name = ctypes.util.find_library("cuda") or "libcuda.so.1"
    try:
        lib = ctypes.CDLL(name)
    except OSError:
        return 0
    count = ctypes.c_int(0)
    if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return 0
    return count.value


def _configure_llvm() -> Path | None:
    """Point Dr.Jit at a good libLLVM; None if there is none (the llvm backend then cannot run)."""
    given = os.environ.get(LLVM_ENV)
    if given:
        path = Path(given)
        match = _LLVM_NAME.match(path.name)
        if path.is_file() and (match is None or int(match.group(1)) >= MIN_LLVM_VERSION):
            return path
        raise BackendError(f"{LLVM_ENV}={given} is not a libLLVM {MIN_LLVM_VERSION}+ file; "
                           "unset it or point it at one (e.g. apt-get install libllvm19)")
    found = find_libllvm()
    if found is None:
        return None
    if "drjit" in sys.modules:
        # Dr.Jit reads the variable when its LLVM backend starts; once it has been imported
        # without it we cannot know which library it will pick, so refuse rather than abort later.
        raise BackendError(f"drjit was imported before {LLVM_ENV} was set; import render.backend and call "
                           "load_mitsuba() first, or export DRJIT_LIBLLVM_PATH=" + str(found))
    os.environ[LLVM_ENV] = str(found)
    return found


def resolve_backend(backend: str = "auto") -> str:
    """The Mitsuba variant name ``backend`` stands for on this machine (no Mitsuba import)."""
    if backend not in BACKENDS:
        raise BackendError(f"unknown render backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "cuda_ad_rgb":
        if cuda_device_count() == 0:
            raise BackendError("backend cuda_ad_rgb was requested but no CUDA GPU/driver was found; "
                               "use backend=llvm_ad_rgb or scalar_rgb (or auto)")
        return backend
    if backend == "llvm_ad_rgb":
        if _configure_llvm() is None:
            raise BackendError(f"backend llvm_ad_rgb needs libLLVM {MIN_LLVM_VERSION}+ (mesa's LLVM 15 aborts the "
                               f"process); none found in {', '.join(_LLVM_DIRS)}. Install one (apt-get install "
                               f"libllvm19), set {LLVM_ENV}, or use backend=scalar_rgb")
        return backend
    if backend == "scalar_rgb":
        return backend
    if cuda_device_count() > 0:
        return "cuda_ad_rgb"
    if _configure_llvm() is not None:
        return "llvm_ad_rgb"
    return "scalar_rgb"


def load_mitsuba(backend: str = "auto") -> ModuleType:
    """The ``mitsuba`` module with its variant set for ``backend`` ("auto" picks the fastest safe one)."""
    if "drjit" not in sys.modules and not os.environ.get(LLVM_ENV):
        # Whatever is asked for now, make a later switch to llvm_ad_rgb in this process safe.
        found = find_libllvm()
        if found is not None:
            os.environ[LLVM_ENV] = str(found)
    variant = resolve_backend(backend)
    import mitsuba as mi

    if variant not in mi.variants():
        raise BackendError(f"this Mitsuba build lacks the {variant} variant (it has {', '.join(mi.variants())})")
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi
