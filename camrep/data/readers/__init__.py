"""Readers of real posed-image datasets on disk, each a view source (`camrep.data.records`).

  gqn           DeepMind GQN TFRecords (rooms), read without TensorFlow
  srn           SRN ShapeNet cars: instance folders of posed renders
  gibson        the authors' Gibson renders: pickled grid metadata per area
  seven_scenes  Microsoft 7-Scenes: pose tables, raw scene layout, 6-DOF pose conversion; its
                packed trajectories (seven_scenes_poses.npz, licence beside it) also drive the
                procedural scene6dof family
  captures      posed captures in the field's formats (NeRF transforms.json, LLFF, COLMAP)
  imageio       image decoding, checks, centre crop and resize shared by the readers
  textio        text-file helpers (4x4 matrices) shared by the readers

Every failure names the file (`camrep.data.errors.DataError`). The sources registry
(`camrep.data.sources`) builds each reader by module path.
"""
