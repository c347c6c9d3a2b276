"""Helper for tests/test_resume.py: `python -m camrep.main FLAGS` with a fault injected.

Usage (from the repository root): python -m tests.resume_script KILL_IN_SAVE FLAGS...

KILL_IN_SAVE: SIGKILL this process in the middle of saving checkpoint KILL_IN_SAVE: after every
file of it is written into Orbax's temporary directory, just before the rename that commits it
(0: no fault). FLAGS are camrep.main's (--config=..., --workdir=..., --config.x=...).
"""

import os
import signal
import sys

kill_step = int(sys.argv.pop(1))

if kill_step:
  from orbax.checkpoint._src.path import atomicity

  _finalize = atomicity.AtomicRenameTemporaryPath.finalize

  async def finalize(self):
    if self.get_final().name == str(kill_step):
      print(f"fault: SIGKILL while committing checkpoint {kill_step}", flush=True)
      os.kill(os.getpid(), signal.SIGKILL)
    return await _finalize(self)

  atomicity.AtomicRenameTemporaryPath.finalize = finalize

from camrep import main  # noqa: E402
from camrep.runtime import cli  # noqa: E402

cli.run(main.main)
