"""7-Scenes (procedural `scene6dof` family by default): six DOFs x, y, z, theta, phi, psi.

Loaded by path (`--config=configs/seven_scenes.py[:quick|:smoke]`) from a checkout. The config
itself, with its commands, run times and expected results, is camrep/configs/seven_scenes.py,
installed with the package and also named by `--config=seven_scenes[:quick|:smoke]`.
"""

from camrep.configs.seven_scenes import get_config  # noqa: F401
