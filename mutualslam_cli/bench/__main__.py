"""``python -m mutualslam_cli.bench``: the ``make bench`` suite (:mod:`mutualslam_cli.bench.suite`)."""

import sys

from mutualslam_cli.bench.suite import main

sys.exit(main())
