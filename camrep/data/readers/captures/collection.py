"""Posed captures as a camrep view source: one capture = one scene (instance).

`python -m camrep.data.prepare --source nerf|llff|colmap --input DIR [DIR ...]` builds a
`CaptureSource` (the car setting: pose = (azimuth, polar) of the camera centre after
`normalize.object_centric`); the `*_6dof` sources put the same captures in the 7-Scenes-like 6-DOF
setting (x, y, z, theta, phi, psi after `normalize.six_dof`) for forward-facing or walk-through
captures.

Splits:

* "train" / "test" (and "val"): a capture with a test split of its own (Blender's
  `transforms_test.json`) keeps its own splits. Any other seen capture holds out every
  `holdout_every`-th of its training views (views 0, k, 2k, ... in file order, LLFF's convention
  with k = 8) as "test" views of that instance: one without split files, and one with a training
  split but no test split (Blender's `transforms_train.json` alone; its val views stay "val").
  holdout_every=0: every view trains (the capture has no held-out view; evaluation refuses a
  dataset in which a seen capture has none, `storage.check_held_out`).
* "test_scenes": the captures named in `unseen` (folder names, or an int: the last N inputs),
  all their views, as novel instances indexed from 0 on their own (as SRN's `cars_test`).

Each capture's split rule, in words, and its per-split view counts are in `describe()` (and so in
the prepared dataset's `camrep_source.json` and prepare's summary).

Inputs: `inputs()` fingerprints what the records are made from (every frame's image and mask
file by size and modification time, pose, intrinsics and own split), so that `prepare` can tell
a changed capture from the one it prepared. One image file in two frames is refused
(`cameras.check_distinct_frames`).

Images: alpha (RGBA) and masks composited on `background`, distortion undone with OpenCV (or
refused with `undistort=False`), then centre-cropped to a square and resized with INTER_AREA to
`image_size`, as the other readers do. The normalisation of each capture, its optical-axis
residuals and its split counts are recorded in the prepared dataset's `camrep_source.json`
(`source_info`).
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from camrep import settings
from camrep.data.errors import DataError
from camrep.data.readers import seven_scenes
from camrep.data.readers.captures import colmap, llff, nerf, normalize
from camrep.data.readers.captures.cameras import (
  Capture,
  CaptureError,
  DistortionError,
  MissingImageError,
  load_frame_image,
  parse_background,
)
from camrep.data.readers.imageio import crop_and_resize
from camrep.data.records import digest

READERS: dict[str, Callable[..., Capture]] = {
  "nerf": nerf.read_capture,
  "llff": llff.read_capture,
  "colmap": colmap.read_capture,
}
SUFFIXES = {settings.CAR: "", settings.SEVEN_SCENES: "_6dof"}
"""The settings captures are read in, and their sources' name suffix: the object-centric car
setting (no position: the cameras on a sphere) and the 6-DOF one."""
SPLIT_ORDER = ("train", "val", "test", "test_scenes")
DEFAULT_HOLDOUT_EVERY = 8
DEFAULT_MARGIN = 0.5
"""6-DOF setting: metres (after scaling) a held-out view may lie outside the training cuboid."""


class CaptureSource:
  """Captures in one format as a `camrep.data.feed.storage.ViewSource`.

  Attributes:
    name: the source name ("nerf", "llff", "colmap", or with "_6dof").
    pose_names: the setting's pose coordinates.
    image_size: side of the records' square images.
    splits: the splits present (subset of `SPLIT_ORDER`).
    captures: the `Capture`s, in input order.
    seen, unseen: indices into `captures` of the training instances and the novel ones.
    normalizations: per capture, the `normalize.Normalization` applied.
    reports: per capture, the normalisation report (residuals; JSON-ready).
  """

  def __init__(
    self,
    inputs: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    format: str,  # noqa: A002  (the capture format's name)
    setting: settings.Setting | str = settings.CAR,
    image_size: int = 128,
    background: str | Sequence[int] | int = "white",
    holdout_every: int = DEFAULT_HOLDOUT_EVERY,
    unseen: Sequence[str] | int = (),
    factor: int | None = None,
    undistort: bool = True,
    use_masks: bool = True,
    max_residual_deg: float = normalize.DEFAULT_MAX_RESIDUAL_DEG,
    extent: Sequence[float] = seven_scenes.DEFAULT_EXTENT,
    margin: float = DEFAULT_MARGIN,
  ):
    """Reads and normalises every capture (images are decoded later, by `iter_views`).

    Args:
      inputs: one capture folder or several (each one instance).
      format: "nerf", "llff" or "colmap".
      setting: `settings.CAR` (object-centric) or `settings.SEVEN_SCENES` (6-DOF), or its name.
      image_size: output side in pixels.
      background: colour behind alpha / masks: "white" (SRN cars' and Blender's), "black",
        "grey", a grey level or (r, g, b).
      holdout_every: k of the every-k-th held-out views (captures without split files).
      unseen: captures (folder names, or the last N inputs) kept whole as "test_scenes".
      factor: LLFF `images_N` folder to read (default: `llff.read_capture`'s choice).
      undistort: undistort distorted cameras (False: refuse them, `DistortionError`).
      use_masks: composite masks where the capture has them.
      max_residual_deg: car setting: refusal threshold (`normalize.object_centric`).
      extent: 6-DOF setting: the grid cuboid (metres) the training positions are scaled into.
      margin: 6-DOF setting: tolerance outside the cuboid for held-out views.

    Raises:
      CaptureError (and its subclasses, e.g. `normalize.NotObjectCentricError`): as the readers
        and the normalisation; DataError for bad arguments.
    """
    if format not in READERS:
      raise DataError(None, f"capture format must be one of {sorted(READERS)}, got {format!r}")
    try:
      setting = settings.get(setting)
    except ValueError as e:
      raise DataError(None, str(e)) from None
    if setting not in SUFFIXES:
      names = [s.name for s in SUFFIXES]
      raise DataError(None, f"setting must be one of {names}, got {setting.name!r}")
    paths = [inputs] if isinstance(inputs, str | os.PathLike) else list(inputs)
    if not paths:
      raise DataError(None, "no capture folder given")
    self.format = format
    self.setting = setting
    self.name = f"{format}{SUFFIXES[setting]}"
    self.pose_names = setting.pose_columns
    self.image_size = int(image_size)
    if self.image_size < 1:
      raise DataError(None, f"image_size must be a positive number of pixels, got {image_size}")
    self.background = parse_background(background)
    self.holdout_every = int(holdout_every)
    if self.holdout_every < 0:
      raise DataError(None, f"holdout_every must be >= 0, got {holdout_every}")
    self.undistort = bool(undistort)
    self.use_masks = bool(use_masks)
    self.extent = tuple(float(e) for e in extent)
    self.margin = float(margin)
    kwargs = {"factor": factor} if format == "llff" else {}
    if factor is not None and format != "llff":
      raise DataError(None, f"factor= is an LLFF option, not one of {format!r}")
    self.captures = [READERS[format](os.fspath(p), **kwargs) for p in paths]
    if not self.undistort:  # refuse before anything is written
      for cap in self.captures:
        bad = [f for f in cap.frames if f.distorted]
        if bad:
          raise DistortionError(
            bad[0].image_path,
            f"{len(bad)} frame(s) of {cap.name} have lens distortion "
            f"{bad[0].distortion.tolist()} (k1, k2, p1, p2, k3, ...) and undistort=False; "
            "drop --config.undistort=False to undistort them with OpenCV",
          )
    names = [c.name for c in self.captures]
    if isinstance(unseen, int):
      if not 0 <= unseen < len(paths):
        raise DataError(None, f"unseen={unseen}: need at least one seen capture of {len(paths)}")
      unseen_idx = list(range(len(paths) - unseen, len(paths)))
    else:
      unknown = [u for u in unseen if u not in names]
      if unknown:
        raise DataError(None, f"unseen names {unknown} are not among the captures {names}")
      unseen_idx = [i for i, n in enumerate(names) if n in set(unseen)]
    self.unseen = unseen_idx
    self.seen = [i for i in range(len(paths)) if i not in unseen_idx]
    if not self.seen:
      raise DataError(None, "every capture is unseen: at least one must train")
    rules = [self._frame_splits(i) for i in range(len(self.captures))]
    self._split_of = [labels for labels, _ in rules]
    self._split_rule = [rule for _, rule in rules]
    for i in self.seen:  # a seen capture trains: without a training view it is an unseen one
      if "train" not in self._split_of[i]:
        raise DataError(
          self.captures[i].root,
          f"{names[i]} has no view left to train on ({self._split_rule[i]}): hold out fewer "
          "views (--config.holdout_every=K, K >= 2; 0 keeps every view for training), or hold "
          "the whole capture out with --config.unseen",
        )
    self.normalizations: list[normalize.Normalization] = []
    self.reports: list[dict[str, Any]] = []
    self._poses: list[np.ndarray] = []
    for i, cap in enumerate(self.captures):
      c2w = cap.c2w()
      where = cap.root
      if not setting.position_dim:
        norm, report = normalize.object_centric(c2w, max_residual_deg=max_residual_deg, where=where)
        poses = setting.poses_from_c2w(norm.apply(c2w))
      else:
        train = np.asarray([s in ("train", "test_scenes") for s in self._split_of[i]])
        norm = normalize.six_dof(c2w[train], extent=self.extent)
        scaled = norm.apply(c2w)
        t_min = seven_scenes.translation_min(scaled[train])
        poses = seven_scenes.c2w_to_dofs(scaled, t_min)
        seven_scenes.check_pose_range(
          poses, [f.image_path for f in cap.frames], extent=self.extent, margin=self.margin
        )
        report = {"translation_min": t_min.tolist(), "extent": list(self.extent)}
      self.normalizations.append(norm)
      self.reports.append(report)
      self._poses.append(poses.astype(np.float32))
    present = {s for split in self._split_of for s in split}
    self.splits = tuple(s for s in SPLIT_ORDER if s in present)

  def _frame_splits(self, i: int) -> tuple[list[str], str]:
    """Capture i's split label per frame, and the rule that made them (in words)."""
    frames = self.captures[i].frames
    own = [f.split for f in frames]
    if i in self.unseen:
      return ["test_scenes"] * len(frames), "whole capture held out (--config.unseen)"
    if "test" in own:
      return [s or "train" for s in own], "its own test split"
    k = self.holdout_every
    why = (
      "it has a training split but no test split"
      if any(s is not None for s in own)
      else "it has no splits of its own"
    )
    if not k:
      return [s or "train" for s in own], f"every view trains ({why}; --config.holdout_every=0)"
    labels, j = [], 0
    for s in own:
      if s in (None, "train"):
        labels.append("test" if j % k == 0 else "train")
        j += 1
      else:
        labels.append(s)
    return labels, f"every {_ordinal(k)} view held out ({why}; --config.holdout_every={k})"

  def _scene_list(self, split: str) -> list[int]:
    self._check_split(split)
    group = self.unseen if split == "test_scenes" else self.seen
    return [i for i in group if split in self._split_of[i]]

  def _check_split(self, split: str) -> None:
    if split not in self.splits:
      raise ValueError(f"split must be one of {self.splits}, got {split!r}")

  def num_scenes(self, split: str) -> int:
    """Instances with views in `split` (seen captures; unseen ones for "test_scenes")."""
    return len(self._scene_list(split))

  def num_views(self, split: str) -> int:
    """Views in `split`."""
    return sum(self._split_of[i].count(split) for i in self._scene_list(split))

  def scene_index(self, capture: int) -> int:
    """The records' scene id of capture `capture` (seen ones 0.., unseen ones 0.. on their own)."""
    group = self.unseen if capture in self.unseen else self.seen
    return group.index(capture)

  def poses(self, capture: int) -> np.ndarray:
    """(N, P) float32 record poses of every frame of a capture, in frame order."""
    return self._poses[capture]

  def iter_views(self, split: str) -> Iterator[dict]:
    """Yields the records of `split`: captures in input order, frames in file order; "view" is
    the frame's position in its capture (Blender: in its split file)."""
    for i in self._scene_list(split):
      cap, labels = self.captures[i], self._split_of[i]
      counters: dict[str, int] = {}
      for frame, label, pose in zip(cap.frames, labels, self._poses[i], strict=True):
        view = counters.get(frame.split or "", 0)
        counters[frame.split or ""] = view + 1
        if label != split:
          continue
        img = load_frame_image(
          frame, background=self.background, undistort=self.undistort, use_mask=self.use_masks
        )
        yield {
          "image": crop_and_resize(img, self.image_size),
          "pose": pose,
          "scene": self.scene_index(i),
          "view": view,
        }

  def describe(self) -> dict[str, Any]:
    """JSON-ready facts recorded with the prepared dataset (`storage.prepare`'s source_info)."""
    out = []
    for i, cap in enumerate(self.captures):
      labels = self._split_of[i]
      out.append(
        {
          "name": cap.name,
          "root": os.path.abspath(cap.root),
          "format": cap.format,
          "role": "unseen" if i in self.unseen else "seen",
          "scene": self.scene_index(i),
          "num_frames": len(cap.frames),
          "splits": {s: labels.count(s) for s in SPLIT_ORDER if s in labels},
          "split_rule": self._split_rule[i],
          "distorted_frames": int(sum(f.distorted for f in cap.frames)),
          "masked_frames": int(sum(f.mask_path is not None for f in cap.frames)),
          "normalization": self.normalizations[i].to_json(),
          **self.reports[i],
        }
      )
    return {
      "kind": "captures",
      "format": self.format,
      "setting": self.setting.name,
      "image_size": self.image_size,
      "background": self.background.astype(int).tolist(),
      "pose_names": list(self.pose_names),
      "captures": out,
    }

  def inputs(self) -> dict[str, Any]:
    """What the records are made from, per capture: a digest per frame (keyed by its image's
    path in the capture) of its image and mask files' sizes and modification times (ns), its
    camera-to-world pose, intrinsics, distortion and own split; and digests of the lot.

    Returns:
      {"digest": str, "captures": [{"name", "root", "digest", "frames": {path: digest}}]}.

    Raises:
      MissingImageError: an image or mask file vanished since the capture was read.
    """
    out = []
    for cap in self.captures:
      frames = {}
      for f in cap.frames:
        entry = {
          "image": _file_stamp(f.image_path),
          "mask": None if f.mask_path is None else _file_stamp(f.mask_path),
          "c2w": np.asarray(f.c2w, np.float64).tolist(),
          "camera": [f.fx, f.fy, f.cx, f.cy, f.width, f.height],
          "distortion": np.asarray(f.distortion, np.float64).tolist(),
          "split": f.split,
        }
        frames[os.path.relpath(f.image_path, cap.root)] = digest(entry)
      root = os.path.abspath(cap.root)
      out.append({"name": cap.name, "root": root, "digest": digest(frames), "frames": frames})
    return {"digest": digest([c["digest"] for c in out]), "captures": out}


def _file_stamp(path: str) -> list[int]:
  """[size in bytes, modification time in ns] of a file."""
  try:
    st = os.stat(path)
  except OSError as e:
    raise MissingImageError(path, f"cannot read ({e.strerror or e})") from None
  return [int(st.st_size), int(st.st_mtime_ns)]


def _ordinal(k: int) -> str:
  """1st, 2nd, 3rd, 4th, ..., 11th, 12th, 13th, 21st, ..."""
  suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
  return f"{k}{suffix}"


def _factory(fmt: str, setting: settings.Setting) -> Callable[..., CaptureSource]:
  def make(inputs, **kwargs) -> CaptureSource:
    if "setting" in kwargs:
      raise DataError(None, f"the setting is chosen by the source name ({fmt} or {fmt}_6dof)")
    return CaptureSource(inputs, format=fmt, setting=setting, **kwargs)

  # The constructor's keywords, less the two the source name fixes (prepare's --config. fields).
  sig = inspect.signature(CaptureSource)
  keep = [p for n, p in sig.parameters.items() if n not in ("format", "setting")]
  make.__signature__ = sig.replace(parameters=keep)
  make.__name__ = f"{fmt}{SUFFIXES[setting]}"
  make.__doc__ = f"`CaptureSource` of {fmt} captures in the {setting.name} setting."
  return make


nerf_car = _factory("nerf", settings.CAR)
llff_car = _factory("llff", settings.CAR)
colmap_car = _factory("colmap", settings.CAR)
nerf_6dof = _factory("nerf", settings.SEVEN_SCENES)
llff_6dof = _factory("llff", settings.SEVEN_SCENES)
colmap_6dof = _factory("colmap", settings.SEVEN_SCENES)

__all__ = ["CaptureError", "CaptureSource"]
