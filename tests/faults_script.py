"""Helper for tests/test_faults.py: a camrep tool's command line with a resource fault injected.

Usage: python tests/faults_script.py FAULT MODULE FLAGS...

FAULT: "none"; "enospc_checkpoint:N" (the disk fills while checkpoint step N is being written:
every later write of Orbax's JSON item fails with ENOSPC, and the other item's writer threads are
slow, as on a loaded machine: each text file of the step waits 1 s before it is written);
"enospc_metrics" (metrics.jsonl cannot grow); "enospc_eval" (the evaluation outputs cannot be
written: numpy / cv2 writers fail).
MODULE: camrep.main, camrep.synthesis.evaluate, ... (its `main` runs under `camrep.runtime.cli`).
"""

import errno
import importlib
import os
import sys

fault = sys.argv.pop(1)
module = sys.argv.pop(1)


def _enospc(*args, **kwargs):
  raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


if fault.startswith("enospc_checkpoint:"):
  import orbax.checkpoint as ocp

  full_from = int(fault.split(":")[1])
  _save_fn = ocp.handlers.JsonCheckpointHandler._save_fn

  async def save_fn(self, x, directory, *args, **kwargs):
    if f"/{full_from}." in str(directory) or str(directory).endswith(f"/{full_from}"):
      print(f"fault: ENOSPC while saving checkpoint {full_from}", flush=True)
      _enospc()
    return await _save_fn(self, x, directory, *args, **kwargs)

  ocp.handlers.JsonCheckpointHandler._save_fn = save_fn
  import time

  from etils.epath import abstract_path

  _write_text = abstract_path.Path.write_text

  def slow_write_text(self, *args, **kwargs):
    if f"/{full_from}.orbax-checkpoint-tmp" in str(self):
      time.sleep(1.0)
    return _write_text(self, *args, **kwargs)

  abstract_path.Path.write_text = slow_write_text
elif fault == "enospc_metrics":
  from camrep.runtime import writers

  writers.MetricWriter.write_scalars = lambda self, *a, **k: _enospc()
elif fault == "enospc_eval":
  import numpy as np

  np.savez = np.savez_compressed = _enospc
  import json

  json.dump = _enospc
elif fault != "none":
  raise SystemExit(f"unknown fault {fault!r}")

from camrep.runtime import cli  # noqa: E402

cli.run(importlib.import_module(module).main)
