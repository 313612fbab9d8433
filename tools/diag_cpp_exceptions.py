"""Does a TORCH_CHECK failing inside a lidarops CPU kernel raise RuntimeError, or crash the process?

On the GPU machine (torch 2.11+cu130, g++ 13.3, CUDA build) every such call segfaulted in runs 1-2 of
2026-11-21 (also ``fps`` with ``lengths=[10, 11]``, whose check runs before any parallel region); on
this machine (torch 2.13 CPU, g++ 12) they raise. Each call runs in a subprocess so that a crash is
reported instead of ending the script. Usage: ``python3 tools/diag_cpp_exceptions.py``.
"""
import faulthandler, sys, subprocess
faulthandler.enable()
code = r'''
import faulthandler; faulthandler.enable()
import torch, lidarops, lidarops.extension as ext
ext.load()
p = torch.randn(2, 10, 3)
L = torch.tensor([10, 10])
for name, f in [
  ("fps lengths 11", lambda: torch.ops.lidarops.fps(p, torch.tensor([10, 11]), torch.tensor([0, 0]), 3, 0)),
  ("fps start 10 m0", lambda: torch.ops.lidarops.fps(p, L, torch.tensor([0, 10]), 3, 0)),
  ("fps start 10 m1", lambda: torch.ops.lidarops.fps(p, L, torch.tensor([0, 10]), 3, 1)),
  ("fps start -1", lambda: torch.ops.lidarops.fps(p, L, torch.tensor([-1, 0]), 3, 0)),
  ("knn k0", lambda: torch.ops.lidarops.knn(p, p, L, L, 0, 0)),
]:
    print(name, flush=True)
    try:
        r = f(); print("  returned", r)
    except Exception as e:
        print("  raised", type(e).__name__, str(e).splitlines()[0])
'''
r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
print(r.stdout, r.stderr[-3000:], "rc", r.returncode)
