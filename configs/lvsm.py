"""A multi-view transformer (LVSM-style) on GQN rooms with one of seven camera conditionings.

Loaded by path (`--config=configs/lvsm.py[:quick|:medium|:smoke]`) from a checkout. The config
itself, with its commands, is camrep/configs/lvsm.py, installed with the package and also named
by `--config=lvsm[:quick|:medium|:smoke]`.
"""

from camrep.configs.lvsm import get_config  # noqa: F401
