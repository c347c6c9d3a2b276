"""GQN rooms: learn the (x, y) polar + yaw pose system by view synthesis (paper section 4.1).

Loaded by path (`--config=configs/gqn.py[:quick|:smoke]`) from a checkout. The config itself, with
its commands, run times and expected results, is camrep/configs/gqn.py, installed with the package
and also named by `--config=gqn[:quick|:smoke]`.
"""

from camrep.configs.gqn import get_config  # noqa: F401
