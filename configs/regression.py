"""Pose regression for the paper's Tables 1 and 2 (sections 4.2 and 5.4, and the supplement).

Loaded by path (`--config=configs/regression.py[:quick|:smoke]`) from a checkout. The config itself,
with its commands, run times and expected results, is camrep/configs/regression.py, installed with
the package and also named by `--config=regression[:quick|:smoke]`.
"""

from camrep.configs.regression import get_config  # noqa: F401
