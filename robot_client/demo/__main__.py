import contextlib
import sys

from .task import main

with contextlib.suppress(KeyboardInterrupt):
    sys.exit(main())
