"""GQN rooms with GQN's own generator (Eslami et al. 2018): the paper's view-synthesis baseline.

Loaded by path (`--config=configs/gqn_convdraw.py[:quick|:smoke]`) from a checkout. The config
itself, with its commands, run times and expected results, is camrep/configs/gqn_convdraw.py,
installed with the package and also named by `--config=gqn_convdraw[:quick|:smoke]`.
"""

from camrep.configs.gqn_convdraw import get_config  # noqa: F401
