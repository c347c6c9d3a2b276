"""Procedural posed-image datasets rendered by `render`: camrep's default data.

Four families mirror the paper's four datasets (the authors' code); each yields view
records (`camrep.data.records`) with the same pose conventions as its real counterpart:

  rooms      like GQN rooms: many square rooms [-1, 1]^2 (textured walls and floor, 1 to 4
             objects), camera free in 2-D at a fixed height and pitch; pose (x, y, yaw).
  object     like ShapeNet cars: many toy cars built from primitives, all facing +x with a bright
             nose, headlights, red tail lights and a rear cabin, so the front is visible; camera
             on a sphere looking at the centre, white background; pose (azimuth, polar).
  area       like Gibson rooms: a few furnished rooms; dense views over a 2 m x 2 m area in the
             middle of each; pose (x, y, yaw) with x, y in [0, 2] m area coordinates.
  scene6dof  like 7-Scenes: one furnished room per 7-Scenes scene, seen along the REAL 7-Scenes
             camera trajectories (`camrep.data.readers.seven_scenes` pose tables); pose = the
             paper's six DOFs from `seven_scenes.c2w_to_dofs`.

Splits: "train"; "test" = different poses of the training scenes (a different random stream,
or the 7-Scenes test trajectories); "test_scenes" = whole held-out scenes (rooms and object),
whose scene ids continue after the training ids (num_train_scenes, num_train_scenes + 1, ...),
so a per-scene table indexed by id never aliases a held-out scene.

Determinism: scene `s` is built from `np.random.default_rng([seed, family, s])` and view `v`
of split `k` from `np.random.default_rng([seed, family, s, k, v])`, so any record can be
regenerated alone and a smaller config's views are a prefix of a larger one's. The renderer
is deterministic (one jit compile per family and image size: see `render`).

Usage:
  family = make_family("rooms", preset="small")
  for record in family.iter_views("train"): ...
  images = family.render_views(scene=0, poses=family.poses("test", 0))

Modules: `catalog` holds the configs, presets and the factory; `families` the four family
classes, `family_base` their shared machinery (splits, pose streams, rendering, view records),
`scenery` the random scene content (materials, light, furnished rooms), `render` the ray caster
and `scene_table` a split's scenes and view poses as arrays for the batch pipeline. The factory,
the configs and the family classes are re-exported here.
"""

from camrep.data.procedural.catalog import COUNTS as COUNTS
from camrep.data.procedural.catalog import FAMILIES as FAMILIES
from camrep.data.procedural.catalog import PRESETS as PRESETS
from camrep.data.procedural.catalog import SMALL_OVERRIDES as SMALL_OVERRIDES
from camrep.data.procedural.catalog import AreaConfig as AreaConfig
from camrep.data.procedural.catalog import ObjectConfig as ObjectConfig
from camrep.data.procedural.catalog import RoomsConfig as RoomsConfig
from camrep.data.procedural.catalog import Scene6DofConfig as Scene6DofConfig
from camrep.data.procedural.catalog import check_counts as check_counts
from camrep.data.procedural.catalog import make_config as make_config
from camrep.data.procedural.catalog import make_family as make_family
from camrep.data.procedural.families import SEVEN_SCENES as SEVEN_SCENES
from camrep.data.procedural.families import AreaFamily as AreaFamily
from camrep.data.procedural.families import ObjectFamily as ObjectFamily
from camrep.data.procedural.families import RoomsFamily as RoomsFamily
from camrep.data.procedural.families import Scene6DofFamily as Scene6DofFamily
from camrep.data.procedural.families import default_pose_dir as default_pose_dir
from camrep.data.procedural.family_base import Layout as Layout
from camrep.data.procedural.family_base import ProceduralFamily as ProceduralFamily
from camrep.data.procedural.family_base import SampledPoseFamily as SampledPoseFamily
