"""Build lidarops: one extension, ``lidarops._C``, with C++ CPU kernels always and CUDA kernels when
a CUDA toolkit and a CUDA build of torch are present (or ``FORCE_CUDA=1``).

Environment:
    FORCE_CUDA=1           build the CUDA kernels even if torch cannot see a GPU (needs nvcc + CUDA torch)
    LIDAROPS_NO_CUDA=1     never build CUDA kernels
    TORCH_CUDA_ARCH_LIST   e.g. "9.0" (honoured by torch.utils.cpp_extension; 9.0 is built as 9.0a, for wgmma)
    MAX_JOBS               parallel compile jobs (ninja)
    LIDAROPS_DEBUG=1       -O0 -g

`make build` runs this through tools/build.py (quiet console, full log in build/build.log). Every
build, `setup.py build_ext --inplace` and `pip install --no-build-isolation -e .` alike, compiles into
build/temp.<platform>-<python>/ with ninja, which tracks headers and flags, so an install after a
build compiles nothing (it links and copies the library, a second).
"""
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig

import torch
import torch.utils.cpp_extension as cpp_extension
from setuptools import setup
from torch.utils.cpp_extension import CUDA_HOME, BuildExtension, CppExtension, CUDAExtension

ROOT = os.path.dirname(os.path.abspath(__file__))
CSRC = os.path.join("csrc")
# The objects of every build, in place or by pip (whose editable and wheel builds otherwise compile
# in a fresh temporary folder): distutils' own name for it, so `setup.py build_ext` finds them too.
BUILD_TEMP = os.path.join(ROOT, "build", f"temp.{sysconfig.get_platform()}-{sys.implementation.cache_tag}")
# Compile time of one file on one core when the ninja log has no earlier time for it: a C++ file on
# the 2-core development machine (7.8 s on average, 2026-11-26; docs/notes/build.md); a CUDA file
# costs far more (60 s is a guess, not measured).
SECONDS_PER_FILE = {".cpp": 9.0, ".cu": 60.0}


def _flag(name: str) -> bool:
    return os.environ.get(name, "0").lower() in ("1", "true", "yes", "on")


def want_cuda() -> tuple[bool, str]:
    if _flag("LIDAROPS_NO_CUDA"):
        return False, "LIDAROPS_NO_CUDA=1"
    if torch.version.cuda is None:
        return False, f"torch {torch.__version__} is a CPU build"
    if CUDA_HOME is None:
        return False, "no CUDA toolkit found (CUDA_HOME / nvcc)"
    if _flag("FORCE_CUDA"):
        return True, "FORCE_CUDA=1"
    if torch.cuda.is_available():
        return True, "CUDA toolkit and a visible GPU"
    if os.environ.get("TORCH_CUDA_ARCH_LIST"):
        return True, "CUDA toolkit and TORCH_CUDA_ARCH_LIST set"
    return False, "no GPU visible (set FORCE_CUDA=1 to build anyway)"


def sources(with_cuda: bool) -> list[str]:
    srcs = sorted(glob.glob(os.path.join(CSRC, "*.cpp")))
    srcs += sorted(glob.glob(os.path.join(CSRC, "ops", "*.cpp")))
    srcs += sorted(glob.glob(os.path.join(CSRC, "ops", "autograd", "*.cpp")))
    srcs += sorted(glob.glob(os.path.join(CSRC, "cpu", "*.cpp")))
    if with_cuda:
        srcs += sorted(glob.glob(os.path.join(CSRC, "cuda", "*.cu")))
    return srcs


def hopper_arch_list() -> bool:
    """Builds compute capability 9.0 as sm_90a (wgmma, the sparse convolutions' Hopper kernel).

    Rewrites TORCH_CUDA_ARCH_LIST (or, unset, the visible GPUs' capabilities): "9.0" becomes "9.0a",
    "9.0+PTX" becomes "9.0a;9.0+PTX" (the PTX stays portable). Returns whether 9.0a is built.
    """
    arch = os.environ.get("TORCH_CUDA_ARCH_LIST", "").strip()
    if not arch and torch.cuda.is_available():
        caps = {torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count())}
        arch = ";".join(f"{a}.{b}" for a, b in sorted(caps))
    if not arch or arch == "native":
        return False
    out = []
    for tok in arch.replace(" ", ";").split(";"):
        if tok == "9.0":
            out.append("9.0a")
        elif tok == "9.0+PTX":
            out += ["9.0a", "9.0+PTX"]
        elif tok:
            out.append(tok)
    os.environ["TORCH_CUDA_ARCH_LIST"] = ";".join(dict.fromkeys(out))
    return "9.0a" in out


def make_extension():
    with_cuda, why = want_cuda()
    debug = _flag("LIDAROPS_DEBUG")
    opt = ["-O0", "-g"] if debug else ["-O3"]
    # -g0 undoes the -g of Python's CFLAGS: debug information for ATen's templates was half of
    # every C++ file's compile time (docs/notes/build.md)
    cxx = opt + ([] if debug else ["-g0"])
    # no contraction into fused multiply-adds (aarch64 compilers contract by default): the CPU kernels
    # round every operation, as the CUDA kernels do with their __*_rn intrinsics, so both give the same bits
    cxx += ["-fopenmp", "-Wno-unused-parameter", "-ffp-contract=off"]
    define_macros = []
    extra = {"cxx": cxx}
    if with_cuda:
        define_macros.append(("WITH_CUDA", None))
        if hopper_arch_list():
            define_macros.append(("LIDAROPS_SM90A", None))
        extra["nvcc"] = opt + ["--expt-relaxed-constexpr", "-lineinfo",
                               "-Xptxas=-warn-spills"]
        ext_cls = CUDAExtension
    else:
        ext_cls = CppExtension
    srcs = sources(with_cuda)
    arch = os.environ.get("TORCH_CUDA_ARCH_LIST", "(torch default)") if with_cuda else "-"
    print(f"[lidarops] torch {torch.__version__}  python {sys.version.split()[0]}", flush=True)
    print(f"[lidarops] CUDA kernels: {'yes' if with_cuda else 'no'} ({why}); arch list: {arch}", flush=True)
    print(f"[lidarops] {len(srcs)} sources: " + ", ".join(os.path.relpath(s, CSRC) for s in srcs), flush=True)
    info = {
        "torch_version": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "with_cuda": with_cuda,
        "cuda_reason": why,
        "arch_list": arch,
    }
    with open(os.path.join(ROOT, "lidarops", "_build_info.json"), "w") as f:
        json.dump(info, f, indent=1)
    return ext_cls(
        name="lidarops._C",
        sources=srcs,
        include_dirs=[os.path.join(ROOT, CSRC, "include")],
        define_macros=define_macros,
        extra_compile_args=extra,
        extra_link_args=["-fopenmp"] + _shared_libstdcxx(),
    )


def _shared_libstdcxx() -> list[str]:
    """Link the C++ runtime dynamically, even under a compiler set up to link it statically.

    On the GPU machine ``CXX=/opt/gcc/bin/g++`` is a wrapper whose ``-B`` directory holds only
    ``libstdc++.a``, so ``-lstdc++`` links libstdc++ statically. The extension then carries a second,
    uninitialised copy of the iostream/locale machinery, and the first ``TORCH_CHECK`` whose message
    formats a number (``std::ostringstream << long``) dies with SIGSEGV inside it instead of raising
    (found with cuda-gdb, 2026-11-21). When the compiler cannot find a shared ``libstdc++.so``, link
    the very ``libstdc++.so.6`` that torch has loaded into this process, by path: it comes before the
    driver's own ``-lstdc++``, so no archive member is pulled in.
    """
    if not sys.platform.startswith("linux"):
        return []
    cxx = os.environ.get("CXX", "c++").split()
    try:
        found = subprocess.run(cxx + ["-print-file-name=libstdc++.so"], capture_output=True,
                               text=True, timeout=60).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return []
    if os.path.isabs(found) and os.path.exists(found):
        return []  # the usual case: the driver links the shared runtime
    with open("/proc/self/maps") as maps:
        loaded = sorted({line.split()[-1] for line in maps if "/libstdc++.so" in line})
    if loaded:
        print(f"[lidarops] {' '.join(cxx)} finds no shared libstdc++; linking {loaded[0]}", flush=True)
        return [loaded[0]]
    return []


def _check_runtime_linkage(path: str) -> None:
    """Refuse an extension that does not load ``libstdc++`` dynamically (see ``_shared_libstdcxx``)."""
    if not sys.platform.startswith("linux") or shutil.which("readelf") is None:
        return
    dyn = subprocess.run(["readelf", "-d", path], capture_output=True, text=True).stdout
    if "libstdc++" not in dyn and "libc++" not in dyn:
        raise RuntimeError(
            f"[lidarops] {path} does not link the C++ runtime dynamically (no libstdc++ in its "
            f"NEEDED entries; CXX={os.environ.get('CXX', '(default)')}). A static copy of libstdc++ "
            "inside a torch extension crashes on the first formatted error message. Build with a "
            "compiler that links libstdc++ dynamically.")
    print(f"[lidarops] {os.path.basename(path)}: libstdc++ linked dynamically", flush=True)


def _ninja_plan(build_directory: str) -> tuple[int, float]:
    """Files that ninja will compile in ``build_directory`` (a dry run) and their expected compile
    time on one core: each file's last time from the ninja log, else ``SECONDS_PER_FILE``."""
    dry = subprocess.run(["ninja", "-n", "-C", build_directory], capture_output=True, text=True, check=True).stdout
    planned = re.findall(r"^\[\d+/\d+\] .* -c (\S+) -o (\S+)", dry, flags=re.M)  # (source, object)
    last = {}
    try:
        with open(os.path.join(build_directory, ".ninja_log")) as log:
            for line in log:
                f = line.rstrip("\n").split("\t")
                if len(f) == 5 and f[0].isdigit() and f[1].isdigit():
                    last[f[3]] = (int(f[1]) - int(f[0])) / 1000
    except OSError:
        pass
    seconds = sum(last.get(obj, SECONDS_PER_FILE.get(os.path.splitext(src)[1], SECONDS_PER_FILE[".cpp"]))
                  for src, obj in planned)
    return len(planned), seconds


def _run_ninja_build_counted(build_directory: str, *args, **kwargs):
    """torch's ninja call, preceded by one line that says how many files it compiles and about how
    long that takes (tools/build.py turns it into make's progress line)."""
    try:
        n, seconds = _ninja_plan(build_directory)
        jobs = int(os.environ.get("MAX_JOBS") or 0) or len(os.sched_getaffinity(0))
        print(f"[lidarops] compiling {n} files with {jobs} jobs, about {seconds / min(max(n, 1), jobs):.0f} s",
              flush=True)
    except (OSError, subprocess.SubprocessError, ValueError, AttributeError):
        pass  # the count is a courtesy: never the reason a build fails
    return _run_ninja_build(build_directory, *args, **kwargs)


_run_ninja_build = getattr(cpp_extension, "_run_ninja_build", None)
if _run_ninja_build is not None:
    cpp_extension._run_ninja_build = _run_ninja_build_counted


class LidaropsBuildExtension(BuildExtension):
    def finalize_options(self):
        super().finalize_options()
        # pip's editable builds pass a fresh temporary folder, where ninja would compile everything
        # again: reuse make build's objects (ninja still recompiles what changed: it tracks headers
        # and flags)
        self.build_temp = BUILD_TEMP

    def build_extension(self, ext):
        super().build_extension(ext)
        _check_runtime_linkage(self.get_ext_fullpath(ext.name))

    def copy_extensions_to_source(self):
        """Replace the in-place library atomically: a process that has it loaded keeps its copy
        (setuptools rewrites the file in place, under any process that has it mapped)."""
        for ext in self.extensions:
            filename = self.get_ext_filename(self.get_ext_fullname(ext.name))
            built = os.path.join(self.build_lib, filename)
            inplace = os.path.join(ROOT, filename)
            tmp = f"{inplace}.{os.getpid()}.tmp"
            shutil.copy2(built, tmp)
            os.replace(tmp, inplace)


setup(
    ext_modules=[make_extension()],
    cmdclass={"build_ext": LidaropsBuildExtension.with_options(use_ninja=True)},
    package_data={"lidarops": ["_build_info.json", "weights/*.pth", "weights/*.pth.xz", "configs/*/*.yaml"]},
    # An explicit root makes an editable install a plain .pth entry for this folder instead of an
    # import hook that maps `lidarops.*` here: under the hook, a copy of the package elsewhere (one
    # without a built library, say) imported this checkout's lidarops._C.
    package_dir={"": "."},
)
