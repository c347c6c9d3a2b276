"""Gibson rooms (procedural `area` family by default): polar (x, y) + yaw over 2 m x 2 m areas.

Loaded by path (`--config=configs/gibson.py[:quick|:smoke]`) from a checkout. The config itself,
with its commands, run times and expected results, is camrep/configs/gibson.py, installed with the
package and also named by `--config=gibson[:quick|:smoke]`.
"""

from camrep.configs.gibson import get_config  # noqa: F401
