#!/usr/bin/env bash
# Why does a TORCH_CHECK failing in a lidarops CPU kernel kill the process on the GPU machine?
# 1. toolchain facts; 2. a native backtrace of the crash (cuda-gdb also debugs host-only code);
# 3. tiny extensions that only throw, built with variants of our flags, each run in a subprocess.
# Usage: bash tools/diag_throw.sh   (after the lidarops build; writes to stdout)
set -u
export PYTHONPATH=$PWD:${PYTHONPATH:-}
echo "== toolchain"
for c in c++ g++ gcc cc; do printf '%s -> ' $c; (command -v $c && $c --version | head -1) || echo none; done
echo "CC=${CC:-} CXX=${CXX:-} LD_LIBRARY_PATH=${LD_LIBRARY_PATH:-}"
python3 - <<'PY'
import torch, sys, sysconfig
print("torch", torch.__version__, "abi", torch._C._GLIBCXX_USE_CXX11_ABI, "python", sys.version.split()[0])
print([l for l in torch.__config__.show().splitlines() if "GCC" in l or "CXX_FLAGS" in l or "compiler" in l.lower()][:4])
PY
so=$(ls lidarops/_C*.so | head -1); echo "ext $so"
ldd "$so" | grep -E "stdc\+\+|gcc_s|gomp|torch|c10" ; readelf -d "$so" | grep -E "RUNPATH|RPATH|NEEDED" | head -20
objdump -s -j .comment "$so" 2>/dev/null | tail -n +4 | head -6
echo "== cuda-gdb backtrace of: fps lengths [10, 11]"
cat > /tmp/crash.py <<'PY'
import torch, lidarops.extension as ext
ext.load()
p = torch.randn(2, 10, 3)
try:
    torch.ops.lidarops.fps(p, torch.tensor([10, 11]), torch.tensor([0, 0]), 3, 0)
    print("returned")
except Exception as e:
    print("raised", type(e).__name__, str(e).splitlines()[0])
PY
timeout 150 cuda-gdb -q -batch -ex "set pagination off" -ex "set print thread-events off" -ex run -ex bt \
  -ex "info sharedlibrary" --args python3 /tmp/crash.py 2>&1 | grep -v -E "^\[New Thread|^\[Thread|Detaching" \
  | grep -E "^#|raised|returned|SIG|stdc|gcc_s|gomp|libc\.so|_C\.|libtorch|libc10|signal" | head -70
echo "== tiny extensions"
mkdir -p /tmp/tiny && cd /tmp/tiny
cat > boom.cpp <<'CPP'
#include <torch/extension.h>
#include <torch/library.h>
at::Tensor boom(const at::Tensor& x) { TORCH_CHECK(x.size(0) < 0, "boom: x has size ", x.sizes()); return x; }
at::Tensor boom_std(const at::Tensor& x) { if (x.size(0) >= 0) throw std::runtime_error("std boom"); return x; }
TORCH_LIBRARY_FRAGMENT(TINYNS, m) { m.def("boom(Tensor x) -> Tensor"); m.def("boom_std(Tensor x) -> Tensor"); }
TORCH_LIBRARY_IMPL(TINYNS, CPU, m) { m.impl("boom", &boom); m.impl("boom_std", &boom_std); }
CPP
cat > k.cu <<'CU'
__global__ void noop_kernel(int* p) { if (p) *p = 1; }
void launch_noop() { noop_kernel<<<1, 1>>>(nullptr); }
CU
cat > build_one.py <<'PY'
import sys, os, torch, subprocess
from torch.utils.cpp_extension import load
name, cflags, lflags, cuda = sys.argv[1], sys.argv[2].split(), sys.argv[3].split(), sys.argv[4] == "1"
src = open("boom.cpp").read().replace("TINYNS", name)
os.makedirs(name, exist_ok=True); open(f"{name}/boom.cpp", "w").write(src)
srcs = [f"{name}/boom.cpp"] + (["k.cu"] if cuda else [])
load(name, srcs, extra_cflags=cflags, extra_ldflags=lflags, is_python_module=False, build_directory=name, verbose=False)
PY
cat > run_one.py <<'PY'
import sys, torch
so, ns, op = sys.argv[1:]
torch.ops.load_library(so)
try:
    getattr(getattr(torch.ops, ns), op)(torch.zeros(2)); print(ns, op, "returned")
except Exception as e:
    print(ns, op, "raised", type(e).__name__)
PY
variants=("v_ours|-O3 -fopenmp|-fopenmp|0" "v_noomp|-O3| |0" "v_ours_cu|-O3 -fopenmp|-fopenmp|1" "v_noomp_cu|-O3| |1" \
          "v_staticgcc|-O3 -fopenmp|-fopenmp -static-libgcc -static-libstdc++|0")
for v in "${variants[@]}"; do IFS='|' read n cf lf cu <<< "$v"; (python3 build_one.py "$n" "$cf" "$lf" "$cu" > "$n.log" 2>&1; echo "built $n rc $?") & done; wait
for v in "${variants[@]}"; do IFS='|' read n cf lf cu <<< "$v"
  so=$(ls $n/*.so 2>/dev/null | head -1); [ -z "$so" ] && { echo "$n: no .so"; tail -5 $n.log; continue; }
  for op in boom boom_std; do python3 run_one.py "$so" "$n" "$op" 2>&1 | tail -1; echo "  rc ${PIPESTATUS[0]}"; done
done
echo "== lidarops with TORCH_SHOW_CPP_STACKTRACES=0/1"
cd - >/dev/null
for s in 0 1; do TORCH_SHOW_CPP_STACKTRACES=$s python3 /tmp/crash.py 2>&1 | tail -1; echo "  rc ${PIPESTATUS[0]}"; done
