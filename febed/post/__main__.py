"""`python -m febed.post RUN_DIR [...]` (the same as `febed post`) and `python -m febed.post study STUDY.toml`."""

import sys

from febed.post.cli import main

sys.exit(main())
