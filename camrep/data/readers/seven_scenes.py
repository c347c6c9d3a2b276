"""Microsoft 7-Scenes: pose tables, the raw scene layout, 6-DOF pose conversion, view records.

On-disk formats (see shared/reference/datasets_and_conventions.md, section 2c):

* `<scene>/TrainSplit.txt`, `<scene>/TestSplit.txt`: one `sequenceK` per line (CRLF), `#` comments.
* `<scene>/seq-XX/frame-NNNNNN.color.png` (640x480 RGB) and `frame-NNNNNN.pose.txt`: a 4x4
  camera-to-world matrix, 4 lines of 4 numbers (`%.7e`, tab separated, CRLF).
* Pose tables `<scene>_{train,test}.txt` (D-SLAM ground truth): one line per frame
  `seq-XX/frame-NNNNNN.color.png qw qx qy qz tx ty tz f`, WORLD-TO-CAMERA as in COLMAP
  (p_cam = R(q) p_world + t, quaternion scalar first).

The 6-DOF pose follows the authors' `compress_dataset.py`: (x, y, z, theta, phi, psi) with the
translation re-based by a per-scene minimum and the Euler angles of transforms3d
`mat2euler(R, 'sxyz')` (static axes, R = Rz(psi) Ry(phi) Rx(theta), the same as scipy's
`Rotation.as_euler('xyz')`), shifted to theta + pi in [0, 2 pi], phi + pi/2 in [0, pi],
psi + pi in [0, 2 pi]. Deviations from the authors' code: the minimum comes from the training
poses only (they used train + test), rotations are projected onto SO(3) first (7-Scenes
rotations are not exactly orthonormal), and poses more than `DEFAULT_MARGIN` (0.5 m) outside the
configured grid cuboid raise a `DataError` (or warn) instead of being silently clipped.
"""

from __future__ import annotations

import logging
import os
import pathlib
import re
from collections.abc import Iterator, Sequence

import numpy as np

from camrep import settings
from camrep.data.errors import DataError
from camrep.data.readers import textio
from camrep.data.readers.imageio import PathLike, check_image_size, crop_and_resize, read_image
from camrep.rotations import euler_sxyz_to_matrix as euler_sxyz_to_matrix
from camrep.rotations import matrix_to_euler_sxyz as matrix_to_euler_sxyz
from camrep.rotations import orthonormalize as orthonormalize
from camrep.rotations import quat_to_matrix

DEFAULT_EXTENT = (4.0, 1.5, 3.0)
"""Grid cuboid (x, y, z) in metres the re-based translations must fit (paper, authors' code)."""

DEFAULT_MARGIN = 0.5
"""Metres a re-based translation may lie outside [0, extent] before the readers refuse it.

The grid's origin is the minimum of the TRAINING positions (no test information), so test
frames can lie below it: on the full D-SLAM trajectories of the seven scenes, up to 0.33 m (fire;
pumpkin 0.28, chess 0.11, stairs 0.10, heads 0.08, redkitchen 0.04, office 0) and up to 0.05 m
above the 4 x 1.5 x 3 m cuboid (redkitchen). 0.5 m admits every real test frame (the position
DOFs extrapolate beyond their end grid points, `camrep.pose.LinearDof`) and still refuses a
mis-scaled or foreign pose. Re-basing on all splits instead would leak the test trajectory into
the training poses and still not fit (redkitchen's all-split y span is 1.54 m > 1.5 m)."""

IMAGE_HW = (480, 640)
"""(height, width) of every 7-Scenes colour frame."""

SPLITS = ("train", "test")
_SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
_FRAME_RE = re.compile(r"^frame-(\d+)\.color\.png$")


def _check_split(split: str) -> None:
  if split not in SPLITS:
    raise ValueError(f"split must be one of {SPLITS}, got {split!r}")


# ---------------------------------------------------------------------------------------------
# Pose conversion.


def translation_min(poses_c2w: np.ndarray) -> np.ndarray:
  """Component-wise minimum camera position; pass TRAINING poses only.

  The authors subtracted the minimum over train + test (`min_loc_all.npy`), which leaks test
  information into the pose re-basing; camrep uses the training frames only.

  Args:
    poses_c2w: (N, 4, 4) camera-to-world matrices, N >= 1.

  Returns:
    (3,) float64 minimum of the translation columns.
  """
  poses = np.asarray(poses_c2w, dtype=np.float64)
  if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] == 0:
    raise ValueError(f"poses_c2w must be (N>=1, 4, 4), got {poses.shape}")
  return poses[:, :3, 3].min(axis=0)


def c2w_to_dofs(poses_c2w: np.ndarray, translation_min: np.ndarray) -> np.ndarray:
  """Camera-to-world matrices -> the paper's 6-DOF pose (x, y, z, theta, phi, psi).

  Translation minus `translation_min`; rotation projected onto SO(3), decomposed as
  R = Rz(psi) Ry(phi) Rx(theta) (transforms3d 'sxyz') and shifted by (pi, pi/2, pi), so that
  theta, psi are in [0, 2 pi] and phi in [0, pi] (authors' `compress_dataset.py`; the
  setting's `camrep.settings.SevenScenes.poses_from_c2w`).

  Args:
    poses_c2w: (N, 4, 4) camera-to-world matrices.
    translation_min: (3,) re-basing offset in metres, from `translation_min` of training poses.

  Returns:
    (N, 6) float64 poses.
  """
  poses = np.asarray(poses_c2w, dtype=np.float64)
  if poses.ndim != 3 or poses.shape[1:] != (4, 4):
    raise ValueError(f"poses_c2w must be (N, 4, 4), got {poses.shape}")
  t_min = np.asarray(translation_min, dtype=np.float64).reshape(3)
  dofs = settings.SEVEN_SCENES.poses_from_c2w(poses)
  dofs[:, :3] -= t_min
  return dofs


def dofs_to_c2w(dofs: np.ndarray, translation_min: np.ndarray) -> np.ndarray:
  """Inverse of `c2w_to_dofs`.

  Args:
    dofs: (N, 6) poses (x, y, z, theta, phi, psi) as produced by `c2w_to_dofs`.
    translation_min: (3,) the offset that was subtracted.

  Returns:
    (N, 4, 4) float64 camera-to-world matrices.
  """
  d = np.asarray(dofs, dtype=np.float64)
  if d.ndim != 2 or d.shape[1] != 6:
    raise ValueError(f"dofs must be (N, 6), got {d.shape}")
  out = settings.SEVEN_SCENES.c2w_from_poses(d)
  out[:, :3, 3] += np.asarray(translation_min, dtype=np.float64).reshape(3)
  return out


def check_pose_range(
  dofs: np.ndarray,
  files: Sequence[PathLike],
  *,
  extent: Sequence[float] = DEFAULT_EXTENT,
  margin: float = 0.0,
  warn_only: bool = False,
) -> int:
  """Checks that re-based poses are finite and their translations lie in [-margin, extent + margin].

  The authors clipped out-of-grid translations silently; camrep refuses them by default.

  Args:
    dofs: (N, 6) poses from `c2w_to_dofs`.
    files: N file names, one per pose, used in messages.
    extent: (3,) cuboid size (x, y, z) in metres.
    margin: tolerance in metres on every side (test frames can lie a little below the training
      minimum: up to 0.32 m in the real 7-Scenes test splits).
    warn_only: log a warning per offending frame instead of raising.

  Returns:
    The number of frames outside the cuboid (only non-zero with `warn_only`).

  Raises:
    DataError: naming the first offending file, for a non-finite pose (always) or an
      out-of-range one (unless `warn_only`).
  """
  d = np.asarray(dofs, dtype=np.float64)
  hi = np.asarray(extent, dtype=np.float64).reshape(3)
  bad = 0
  for i, row in enumerate(d):
    if not np.all(np.isfinite(row)):
      raise DataError(files[i], f"non-finite pose {row.tolist()}")
    t = row[:3]
    if np.any(t < -margin) or np.any(t > hi + margin):
      msg = (
        f"re-based translation {np.round(t, 4).tolist()} m lies outside the grid cuboid "
        f"[0, {hi.tolist()}] m (margin {margin} m)"
      )
      if not warn_only:
        raise DataError(files[i], msg)
      logging.warning("%s: %s", os.fspath(files[i]), msg)
      bad += 1
  return bad


# ---------------------------------------------------------------------------------------------
# File readers.


def read_pose_table(path: PathLike) -> tuple[list[str], np.ndarray]:
  """Reads a D-SLAM pose table `<scene>_{train,test}.txt` (world-to-camera, COLMAP convention).

  Lines are `seq-XX/frame-NNNNNN.color.png qw qx qy qz tx ty tz f`; blank and `#` lines are
  skipped. File order is kept (the tables are not sorted).

  Args:
    path: the table file.

  Returns:
    names: N frame names as written (e.g. "seq-02/frame-000226.color.png").
    poses_c2w: (N, 4, 4) float64 camera-to-world matrices (rotation from the normalised
      quaternion; centre c = -R^T t).

  Raises:
    DataError: for a missing file, a malformed line, a zero or non-finite quaternion, or no rows.
  """
  try:
    with open(path) as f:
      lines = f.read().splitlines()
  except OSError as e:
    raise DataError(path, f"cannot read pose table ({e.strerror or e})") from e
  names, rows = [], []
  for lineno, line in enumerate(lines, start=1):
    s = line.strip()
    if not s or s.startswith("#"):
      continue
    tok = s.split()
    try:
      if len(tok) != 9:
        raise ValueError(f"{len(tok)} fields")
      vals = [float(v) for v in tok[1:8]]
    except ValueError as e:
      raise DataError(
        path, f"line {lineno}: expected 'name qw qx qy qz tx ty tz f', got {s!r} ({e})"
      ) from e
    q = np.array(vals[:4])
    if not np.all(np.isfinite(vals)) or np.linalg.norm(q) < 1e-8:
      raise DataError(path, f"line {lineno}: non-finite pose or zero quaternion in {s!r}")
    names.append(tok[0])
    rows.append(vals)
  if not rows:
    raise DataError(path, "pose table has no rows")
  return names, table_rows_to_c2w(np.array(rows, dtype=np.float64))


def table_rows_to_c2w(arr: np.ndarray) -> np.ndarray:
  """Pose-table rows (N, 7) `qw qx qy qz tx ty tz` (world-to-camera) -> (N, 4, 4) camera-to-world:
  rotation from the normalised quaternion, centre c = -R^T t."""
  rot_w2c = quat_to_matrix(arr[:, :4])
  rot_c2w = np.swapaxes(rot_w2c, -1, -2)
  poses = np.zeros((len(arr), 4, 4))
  poses[:, :3, :3] = rot_c2w
  poses[:, :3, 3] = -np.einsum("nij,nj->ni", rot_c2w, arr[:, 4:7])
  poses[:, 3, 3] = 1.0
  return poses


# The pose tables of all seven scenes, shipped with camrep (`pack_pose_tables` wrote the file):
# each table's 7 numbers per frame as integers of 1e-6 (the text tables have 6 decimals, so
# n / 1e6 gives back exactly the float the text parses to) and the frame names as
# (sequence, frame) integers. Licence: Microsoft Research 7-Scenes non-commercial licence,
# LICENSE-7scenes.rtf beside the file.
PACKED_POSES = os.path.join(os.path.dirname(__file__), "seven_scenes_poses.npz")
_POSE_SCALE = 1_000_000
_FRAME_NAME = re.compile(r"^seq-(\d+)/frame-(\d+)\.color\.png$")


def pack_pose_tables(table_dir: PathLike, out: PathLike = PACKED_POSES) -> dict[str, int]:
  """Packs every `<scene>_{train,test}.txt` of `table_dir` into one compressed .npz (exact).

  Returns:
    {"<scene>_<split>": number of frames}.

  Raises:
    DataError: a table is malformed, a frame name is not `seq-XX/frame-NNNNNN.color.png`, or a
      value has more than 6 decimals (it would not round-trip exactly).
  """
  arrays = {}
  for path in sorted(pathlib.Path(table_dir).glob("*_t*.txt")):
    names, _ = read_pose_table(path)
    vals = np.array([line.split()[1:8] for line in _table_lines(path)], dtype=np.float64)
    ints = np.round(vals * _POSE_SCALE).astype(np.int64)
    if not np.array_equal(ints / _POSE_SCALE, vals):
      raise DataError(path, "values with more than 6 decimals cannot be packed exactly")
    frames = []
    for n in names:
      m = _FRAME_NAME.match(n)
      if not m:
        raise DataError(path, f"frame name {n!r} is not seq-XX/frame-NNNNNN.color.png")
      frames.append((int(m.group(1)), int(m.group(2))))
    arrays[path.stem] = np.concatenate([np.array(frames, np.int64), ints], axis=1).astype(np.int32)
  if not arrays:
    raise DataError(table_dir, "no <scene>_{train,test}.txt pose tables found")
  np.savez_compressed(out, **arrays)
  return {k: len(v) for k, v in arrays.items()}


def _table_lines(path: PathLike) -> list[str]:
  with open(path) as f:
    return [s for s in (line.strip() for line in f) if s and not s.startswith("#")]


def packed_pose_table(
  scene: str, split: str, path: PathLike = PACKED_POSES
) -> tuple[list[str], np.ndarray]:
  """`read_pose_table` of `<scene>_<split>.txt`, from the pose tables shipped with camrep.

  Returns:
    names: N frame names ("seq-02/frame-000226.color.png"); poses_c2w: (N, 4, 4) float64,
    identical to reading the text table.

  Raises:
    DataError: the file is missing or holds no such table.
  """
  key = f"{scene}_{split}"
  try:
    with np.load(path) as z:
      if key not in z.files:
        raise DataError(path, f"no pose table {key!r}; it holds {sorted(z.files)}")
      rows = z[key]
  except OSError as e:
    raise DataError(path, f"cannot read the packed pose tables ({e.strerror or e})") from e
  names = [f"seq-{q:02d}/frame-{f:06d}.color.png" for q, f in rows[:, :2].tolist()]
  return names, table_rows_to_c2w(rows[:, 2:].astype(np.float64) / _POSE_SCALE)


def read_pose_file(path: PathLike) -> np.ndarray:
  """Reads one `frame-NNNNNN.pose.txt` (16 numbers, camera-to-world).

  Args:
    path: the pose file.

  Returns:
    (4, 4) float64 camera-to-world matrix (rotation as stored, not orthonormalised).

  Raises:
    DataError: if the file is missing, does not hold 16 numbers, is non-finite, or its last row
      is not (0, 0, 0, 1).
  """
  m = textio.read_matrix_4x4(path)
  if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
    raise DataError(path, f"last row of the pose is {m[3].tolist()}, expected [0, 0, 0, 1]")
  return m


def read_split_file(path: PathLike) -> list[int]:
  """Parses `TrainSplit.txt` / `TestSplit.txt`: `sequenceK` lines -> [K, ...] in file order.

  Blank lines and `#` comments are skipped; any line ending (CRLF in the release) is accepted.

  Raises:
    DataError: for a missing file, a malformed line, or no sequences.
  """
  try:
    with open(path, newline=None) as f:
      lines = f.read().splitlines()
  except OSError as e:
    raise DataError(path, f"cannot read split file ({e.strerror or e})") from e
  seqs = []
  for lineno, line in enumerate(lines, start=1):
    s = line.strip()
    if not s or s.startswith("#"):
      continue
    m = re.fullmatch(r"sequence(\d+)", s, flags=re.IGNORECASE)
    if m is None:
      raise DataError(path, f"line {lineno}: expected 'sequenceK', got {s!r}")
    seqs.append(int(m.group(1)))
  if not seqs:
    raise DataError(path, "split file lists no sequences")
  return seqs


def read_split(scene_dir: PathLike, split: str) -> dict:
  """Lists the frames of one split of a raw 7-Scenes scene directory.

  Args:
    scene_dir: e.g. `.../7scenes/stairs`.
    split: "train" (TrainSplit.txt) or "test" (TestSplit.txt).

  Returns:
    dict(image_paths=list[str] of N colour frames ordered by sequence number then frame number,
         poses_c2w=(N, 4, 4) float64 camera-to-world matrices from the `.pose.txt` files).

  Raises:
    DataError: for a missing scene / split file / sequence directory, an empty sequence, a colour
      frame without its pose file, or a bad pose file.
  """
  _check_split(split)
  scene_dir = os.fspath(scene_dir)
  if not os.path.isdir(scene_dir):
    raise DataError(scene_dir, "7-Scenes scene directory does not exist")
  seqs = sorted(set(read_split_file(os.path.join(scene_dir, _SPLIT_FILES[split]))))
  image_paths, poses = [], []
  for k in seqs:
    seq_dir = os.path.join(scene_dir, f"seq-{k:02d}")
    if not os.path.isdir(seq_dir):
      raise DataError(seq_dir, f"sequence {k} listed in {_SPLIT_FILES[split]} is missing")
    frames = sorted(
      (int(m.group(1)), name)
      for name in os.listdir(seq_dir)
      if (m := _FRAME_RE.match(name)) is not None
    )
    if not frames:
      raise DataError(seq_dir, "sequence directory holds no frame-NNNNNN.color.png files")
    for _, name in frames:
      img_path = os.path.join(seq_dir, name)
      pose_path = img_path[: -len(".color.png")] + ".pose.txt"
      if not os.path.isfile(pose_path):
        raise DataError(pose_path, "pose file missing for colour frame")
      image_paths.append(img_path)
      poses.append(read_pose_file(pose_path))
  return dict(image_paths=image_paths, poses_c2w=np.stack(poses))


def pose_path_of(image_path: PathLike) -> str:
  """`.../frame-NNNNNN.color.png` -> `.../frame-NNNNNN.pose.txt`."""
  p = os.fspath(image_path)
  return p[: -len(".color.png")] + ".pose.txt"


def iter_scene_views(
  scene_dir: PathLike,
  split: str,
  *,
  scene: int = 0,
  image_size: int = 128,
  extent: Sequence[float] = DEFAULT_EXTENT,
  margin: float = DEFAULT_MARGIN,
  warn_only: bool = False,
) -> Iterator[dict]:
  """Yields the view records of one split of one scene.

  Images: 640x480 RGB, centre-cropped to 480x480 and resized with INTER_AREA to `image_size`.
  Poses: `c2w_to_dofs` with the minimum of this scene's TRAINING translations (also for the test
  split), range-checked against `extent` before any image is decoded.

  Args:
    scene_dir: raw scene directory.
    split: "train" or "test".
    scene: value of the records' "scene" field.
    image_size: output side length in pixels.
    extent: (3,) grid cuboid in metres.
    margin: range-check tolerance in metres (see `check_pose_range`).
    warn_only: warn instead of raising for translations outside the cuboid.

  Yields:
    View records {"image": uint8 (S, S, 3), "pose": float32 (6,), "scene": int, "view": int},
    "view" being the frame's index within the split (sequence-then-frame order).

  Raises:
    DataError: as `read_split`, `check_pose_range`, or for an undecodable / non-640x480 image.
  """
  data = read_split(scene_dir, split)
  train = data if split == "train" else read_split(scene_dir, "train")
  t_min = translation_min(train["poses_c2w"])
  dofs = c2w_to_dofs(data["poses_c2w"], t_min)
  check_pose_range(
    dofs,
    [pose_path_of(p) for p in data["image_paths"]],
    extent=extent,
    margin=margin,
    warn_only=warn_only,
  )
  for view, (path, pose) in enumerate(zip(data["image_paths"], dofs, strict=True)):
    img = read_image(path)
    check_image_size(img, IMAGE_HW, path)
    yield {
      "image": crop_and_resize(img, image_size),
      "pose": pose.astype(np.float32),
      "scene": int(scene),
      "view": view,
    }


class SevenScenes:
  """The 7-Scenes reader: one scene index per scene directory under `root`.

  Attributes:
    name: "seven_scenes".
    pose_names: (x, y, z, theta, phi, psi).
    image_size: side length of the records' images.
    scenes: scene directory names, in scene-index order.
  """

  name = "seven_scenes"
  pose_names = settings.SEVEN_SCENES.pose_columns
  splits = SPLITS

  def __init__(
    self,
    root: PathLike,
    *,
    scenes: Sequence[str] | None = None,
    image_size: int = 128,
    extent: Sequence[float] = DEFAULT_EXTENT,
    margin: float = DEFAULT_MARGIN,
    warn_only: bool = False,
  ):
    """Initialises the reader.

    Args:
      root: directory holding one folder per scene (e.g. chess, fire, ..., stairs).
      scenes: scene folder names in scene-index order; default: every sub-directory of `root`
        holding a TrainSplit.txt, sorted.
      image_size: output side length in pixels.
      extent: (3,) grid cuboid (x, y, z) in metres for the range check.
      margin: range-check tolerance in metres (see `check_pose_range`; default
        `DEFAULT_MARGIN`, which admits every real 7-Scenes test frame).
      warn_only: warn instead of raising for translations outside the cuboid.

    Raises:
      DataError: if `root` (or a named scene) is missing, or no scene is found.
    """
    self.root = os.fspath(root)
    if not os.path.isdir(self.root):
      raise DataError(self.root, "7-Scenes root directory does not exist")
    if scenes is None:
      scenes = sorted(
        d
        for d in os.listdir(self.root)
        if os.path.isfile(os.path.join(self.root, d, "TrainSplit.txt"))
      )
      if not scenes:
        raise DataError(self.root, "no scene directory with a TrainSplit.txt found")
    for s in scenes:
      if not os.path.isdir(os.path.join(self.root, s)):
        raise DataError(os.path.join(self.root, s), "7-Scenes scene directory does not exist")
    self.scenes = list(scenes)
    self.image_size = int(image_size)
    self.extent = tuple(float(e) for e in extent)
    self.margin = float(margin)
    self.warn_only = bool(warn_only)

  def num_scenes(self, split: str) -> int:
    """Number of scenes (the same for both splits)."""
    _check_split(split)
    return len(self.scenes)

  def iter_views(self, split: str) -> Iterator[dict]:
    """Yields the view records of `split`, scene by scene, in a deterministic order."""
    _check_split(split)
    for index, s in enumerate(self.scenes):
      yield from iter_scene_views(
        os.path.join(self.root, s),
        split,
        scene=index,
        image_size=self.image_size,
        extent=self.extent,
        margin=self.margin,
        warn_only=self.warn_only,
      )
