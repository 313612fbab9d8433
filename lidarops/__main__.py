import sys

from lidarops.cli import main

sys.exit(main())
