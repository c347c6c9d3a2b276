"""Helper for tests/test_regression_resume.py: `python -m camrep.regression FLAGS` whose steps are
slowed down on the host (SLOW_STEP_S seconds each, default 0.05), so that a test can signal or
kill it between two checkpoints. Nothing it computes changes.

Usage (from the repository root): python -m tests.regression_resume_script FLAGS...
"""

import os
import time

from camrep.runtime import progress

_update = progress.Progress.update
_pause = float(os.environ.get("SLOW_STEP_S", "0.05"))


def _slow_update(self, step):
  time.sleep(_pause)
  return _update(self, step)


progress.Progress.update = _slow_update

from camrep.regression import __main__ as regression_main  # noqa: E402
from camrep.runtime import cli  # noqa: E402

cli.run(regression_main.main)
