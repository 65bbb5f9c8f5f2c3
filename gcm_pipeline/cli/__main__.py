"""``python -m gcm_pipeline.cli``: the ``gcm`` command line."""

import sys

from gcm_pipeline.cli import main

sys.exit(main())
