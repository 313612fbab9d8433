"""Build lidarops: one extension, ``lidarops._C``, with C++ CPU kernels always and CUDA kernels when
a CUDA toolkit and a CUDA build of torch are present (or ``FORCE_CUDA=1``).

Environment:
    FORCE_CUDA=1           build the CUDA kernels even if torch cannot see a GPU (needs nvcc + CUDA torch)
    LIDAROPS_NO_CUDA=1     never build CUDA kernels
    TORCH_CUDA_ARCH_LIST   e.g. "9.0" (honoured by torch.utils.cpp_extension; 9.0 is built as 9.0a, for wgmma)
    MAX_JOBS               parallel compile jobs (ninja)
    LIDAROPS_DEBUG=1       -O0 -g
"""
import glob
import json
import os
import shutil
import subprocess
import sys

import torch
from setuptools import setup
from torch.utils.cpp_extension import CUDA_HOME, BuildExtension, CppExtension, CUDAExtension

ROOT = os.path.dirname(os.path.abspath(__file__))
CSRC = os.path.join("csrc")


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
    # no contraction into fused multiply-adds (aarch64 compilers contract by default): the CPU kernels
    # round every operation, as the CUDA kernels do with their __*_rn intrinsics, so both give the same bits
    cxx = opt + ["-fopenmp", "-Wno-unused-parameter", "-ffp-contract=off"]
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


class LidaropsBuildExtension(BuildExtension):
    def build_extension(self, ext):
        super().build_extension(ext)
        _check_runtime_linkage(self.get_ext_fullpath(ext.name))


setup(
    ext_modules=[make_extension()],
    cmdclass={"build_ext": LidaropsBuildExtension.with_options(use_ninja=True)},
    package_data={"lidarops": ["_build_info.json", "weights/*.pth"]},
)
