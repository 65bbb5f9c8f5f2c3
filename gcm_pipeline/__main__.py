"""``python -m gcm_pipeline``: the ``gcm`` command line."""

from __future__ import annotations

import sys

from gcm_pipeline.cli import main

if __name__ == "__main__":
    sys.exit(main())
