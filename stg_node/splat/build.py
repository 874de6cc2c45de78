"""Builds the C++/OpenMP CPU kernels on first use and caches the result on disk.

The sources in ``csrc/`` are compiled with ``torch.utils.cpp_extension.load`` (ninja + the
machine's C++ compiler) into ``$STG_SPLAT_CACHE`` (default ``~/.cache/stg_node/splat``, or
under ``$XDG_CACHE_HOME``). The cache directory is keyed by a hash of the sources, the
compiler flags (including the instruction-set flags), the compiler's version, and the torch
version and C++ ABI, so a changed source, compiler or torch triggers a rebuild and never loads
a stale library. The operators are registered under a namespace derived from the same key,
so two builds can never clash inside one process.

Instruction set: we do **not** use ``-march=native`` (a cache in a shared home directory may be
loaded by a different CPU). Instead the x86-64 feature level is read from ``/proc/cpuinfo``:
AVX2+FMA machines get ``-mavx2 -mfma -mf16c -mbmi -mbmi2`` (x86-64-v3), others the portable
baseline; the flags are part of the key, so a v3 build is never loaded on an older CPU.
``STG_SPLAT_ARCH_FLAGS`` overrides the choice (e.g. ``-march=native`` on a dedicated machine,
or an empty string for the portable baseline).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import platform
import shlex
import shutil
import subprocess
import sys
import threading
from pathlib import Path

from ..progress import wait_with_progress
from .types import BackendUnavailable

log = logging.getLogger(__name__)

ENV_CACHE = "STG_SPLAT_CACHE"
ENV_ARCH_FLAGS = "STG_SPLAT_ARCH_FLAGS"
CSRC_DIR = Path(__file__).resolve().parent / "csrc"
SOURCES = (
    "splat_kernels.cpp",
    "image_filter.cpp",
    "edge_loss.cpp",
    "densify_stats.cpp",
    "skinning.cpp",
    "small_mlp.cpp",
    "sphere_occlusion.cpp",
    "distant_shading.cpp",
    "kinematics.cpp",
    "scale_cap.cpp",
    "splat_bindings.cpp",
)
HEADERS = (
    "splat_kernels.h",
    "image_filter.h",
    "edge_loss.h",
    "densify_stats.h",
    "skinning.h",
    "small_mlp.h",
    "sphere_occlusion.h",
    "distant_shading.h",
    "kinematics.h",
    "scale_cap.h",
    "fast_math.h",
)
# -ffp-contract=off: the forward and backward passes must compute alpha bit-identically (the
# kernels fuse multiply-adds explicitly, in helpers both passes share).
# -fno-trapping-math: lets the compiler if-convert float selects, so the lane loops vectorise
# (it assumes no FP exception is observed; results are unchanged).
BASE_CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math")
BASE_LDFLAGS = ("-fopenmp",)
X86_V3_FEATURES = ("avx2", "fma", "f16c", "bmi1", "bmi2")
X86_V3_FLAGS = ("-mavx2", "-mfma", "-mf16c", "-mbmi", "-mbmi2")


class ExtensionUnavailable(BackendUnavailable):
    """The CPU kernels cannot be built or loaded here; ``reason`` says why, ``log_path`` where."""

    def __init__(self, message: str, reason: str, log_path: Path | None = None):
        super().__init__(message)
        self.reason = reason
        self.log_path = log_path


def cache_root() -> Path:
    """Where built kernels live: $STG_SPLAT_CACHE, else $XDG_CACHE_HOME/stg_node/splat."""
    explicit = os.environ.get(ENV_CACHE)
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "stg_node" / "splat"


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


def arch_flags() -> list[str]:
    """Instruction-set flags for this CPU (see the module docstring)."""
    override = os.environ.get(ENV_ARCH_FLAGS)
    if override is not None:
        return shlex.split(override)
    if platform.machine().lower() in ("x86_64", "amd64") and set(X86_V3_FEATURES) <= _cpu_flags():
        return list(X86_V3_FLAGS)
    return []


def compiler() -> str:
    """The C++ compiler torch's extension builder will use ($CXX, else c++)."""
    return os.environ.get("CXX", "c++")


def _compiler_version(cxx: str) -> str:
    try:
        out = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError) as exc:
        raise ExtensionUnavailable(
            f"the C++ compiler {cxx!r} does not run ({exc})", reason="no-compiler"
        ) from exc
    first = (out.stdout or out.stderr).strip().splitlines()
    return first[0] if first else cxx


def build_key(source_dir: Path, cflags: list[str], compiler_version: str) -> str:
    """Hash of everything that decides the built binary."""
    import torch

    h = hashlib.sha256()
    for name in SOURCES + HEADERS:
        h.update(name.encode())
        h.update((source_dir / name).read_bytes())
    h.update(" ".join(cflags).encode())
    h.update(" ".join(BASE_LDFLAGS).encode())
    h.update(compiler_version.encode())
    h.update(torch.__version__.encode())
    h.update(str(torch._C._GLIBCXX_USE_CXX11_ABI).encode())
    h.update(platform.machine().encode())
    return h.hexdigest()[:16]


@contextlib.contextmanager
def _ninja_on_path():
    """Put the pip `ninja` package's binary (or this Python's bin dir) on PATH for the build:
    torch looks for a `ninja` executable, which an unactivated venv does not expose."""
    old = os.environ.get("PATH", "")
    extra = [str(Path(sys.executable).parent)]
    try:
        import ninja  # the PyPI package ships the binary

        extra.insert(0, ninja.BIN_DIR)
    except ImportError:
        pass
    os.environ["PATH"] = os.pathsep.join([*extra, old]) if old else os.pathsep.join(extra)
    try:
        yield
    finally:
        os.environ["PATH"] = old


class CpuKernels:
    """The loaded operators (``torch.ops.<namespace>``) plus what they were built with."""

    def __init__(self, ops, namespace: str, library: Path, cflags: list[str]):
        self.ops = ops
        self.namespace = namespace
        self.library = library
        self.cflags = cflags

    def __repr__(self) -> str:
        return f"CpuKernels({self.namespace}, {self.library})"


def build_extension(source_dir: Path = CSRC_DIR, cache_dir: Path | None = None) -> CpuKernels:
    """Compile (or reuse from the cache) and load the kernels; ExtensionUnavailable if not."""
    import torch
    from torch.utils import cpp_extension

    cxx = compiler()
    if shutil.which(cxx) is None:
        raise ExtensionUnavailable(
            f"no C++ compiler found (looked for {cxx!r}; set CXX to choose one)", reason="no-compiler"
        )
    version = _compiler_version(cxx)
    cflags = [*BASE_CFLAGS, *arch_flags()]
    key = build_key(source_dir, cflags, version)
    namespace = f"stg_splat_{key}"
    build_dir = (cache_dir or cache_root()) / namespace
    build_dir.mkdir(parents=True, exist_ok=True)
    library = build_dir / f"{namespace}.so"
    log_path = build_dir / "build.log"

    if not library.exists():
        with _ninja_on_path():
            _compile(cpp_extension, namespace, source_dir, cflags, build_dir, log_path, cxx, version)
    else:
        try:
            torch.ops.load_library(str(library))
        except OSError as exc:
            raise ExtensionUnavailable(
                f"the cached CPU splat kernels in {library} do not load ({exc}); delete {build_dir}",
                reason="build-failed",
                log_path=log_path,
            ) from exc
    ops = getattr(torch.ops, namespace)
    return CpuKernels(ops, namespace, library, cflags)


def _compile(cpp_extension, namespace, source_dir, cflags, build_dir, log_path, cxx, version) -> None:
    """Run torch's extension builder; its failure becomes ExtensionUnavailable naming the log."""
    if not cpp_extension.is_ninja_available():
        raise ExtensionUnavailable(
            "ninja is not installed (torch needs it to build C++ extensions; "
            "`pip install ninja` or your system's ninja package)",
            reason="no-compiler",
        )
    log.info(
        "building the CPU splat kernels with %s %s (once; cached in %s)", cxx, " ".join(cflags), build_dir
    )
    try:
        wait_with_progress(
            lambda: cpp_extension.load(
                name=namespace,
                sources=[str(source_dir / name) for name in SOURCES],
                extra_cflags=[*cflags, f"-DSTG_SPLAT_NS={namespace}"],
                extra_ldflags=list(BASE_LDFLAGS),
                build_directory=str(build_dir),
                is_python_module=False,
                verbose=False,
            ),
            desc="building the CPU splat kernels",
        )
    except Exception as exc:  # cpp_extension raises RuntimeError with the compiler output
        log_path.write_text(f"compiler: {cxx} ({version})\nflags: {' '.join(cflags)}\n\n{exc}\n")
        raise ExtensionUnavailable(
            f"building the CPU splat kernels failed; the compiler output is in {log_path}",
            reason="build-failed",
            log_path=log_path,
        ) from exc
    log_path.write_text(f"compiler: {cxx} ({version})\nflags: {' '.join(cflags)}\nbuilt OK\n")


_lock = threading.Lock()
_kernels: CpuKernels | None = None
_failure: ExtensionUnavailable | None = None


def kernels_take(*tensors) -> bool:
    """Whether the CPU kernels take these tensors: float32 CPU ones (None entries are ignored) and
    kernels that build here. Raises nothing; the build's failure is remembered."""
    import torch

    if any(t is not None and (t.device.type != "cpu" or t.dtype != torch.float32) for t in tensors):
        return False
    try:
        load_kernels()
    except BackendUnavailable:
        return False
    return True


def load_kernels() -> CpuKernels:
    """The process-wide kernels, built on first call; the first failure is remembered."""
    global _kernels, _failure
    with _lock:
        if _kernels is not None:
            return _kernels
        if _failure is not None:
            raise _failure
        try:
            _kernels = build_extension()
        except ExtensionUnavailable as exc:
            _failure = exc
            raise
        return _kernels
