"""ShapeNet car (procedural `object` family by default): azimuth + polar-angle pose system.

Loaded by path (`--config=configs/shapenet_car.py[:quick|:smoke]`) from a checkout. The config
itself, with its commands, run times and expected results, is camrep/configs/shapenet_car.py,
installed with the package and also named by `--config=shapenet_car[:quick|:smoke]`.
"""

from camrep.configs.shapenet_car import get_config  # noqa: F401
