"""Run an OpenPCDet script with lidarops.compat.pcdet serving its compiled ops:

    python tools/upstream/openpcdet/with_faces.py OPENPCDET/tools/train.py [its arguments]

(``lidarops.compat.pcdet.install()``, then the script as ``__main__``, from its own folder.)
"""
from __future__ import annotations

import os
import runpy
import sys
from pathlib import Path

script = Path(sys.argv[1]).resolve()
sys.path.insert(0, str(script.parent.parent))  # the checkout: `import pcdet`
sys.path.insert(0, str(script.parent))  # its tools/ folder: train_utils, eval_utils
import lidarops.compat.pcdet  # noqa: E402

lidarops.compat.pcdet.install()
os.chdir(script.parent)
sys.argv = [str(script)] + sys.argv[2:]
runpy.run_path(str(script), run_name="__main__")
