"""Posed captures as a camrep view source: one capture = one scene (instance).

`python -m camrep.data.prepare --source nerf|llff|colmap --input DIR [DIR ...]` builds a
`CaptureSource` (the car setting: pose = (azimuth, polar) of the camera centre after
`normalize.object_centric`); the `*_6dof` sources put the same captures in the 7-Scenes-like 6-DOF
setting (x, y, z, theta, phi, psi after `normalize.six_dof`) for forward-facing or walk-through
captures.

Splits:

* "train" / "test" (and "val"): a capture's own split files where it has them (Blender's
  `transforms_{train,val,test}.json`); otherwise every `holdout_every`-th view (views 0, k, 2k, ...
  by file order, LLFF's convention with k = 8) is a held-out "test" view of that seen instance,
  the rest "train" (holdout_every=0: every view trains).
* "test_scenes": the captures named in `unseen` (folder names, or an int: the last N inputs),
  all their views, as novel instances indexed from 0 on their own (as SRN's `cars_test`).

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
from camrep.data import seven_scenes
from camrep.data.captures import colmap, llff, nerf, normalize
from camrep.data.captures.cameras import (
  Capture,
  CaptureError,
  DistortionError,
  load_frame_image,
  parse_background,
)
from camrep.data.errors import DataError
from camrep.data.imageio import crop_and_resize

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
  """Captures in one format as a `camrep.data.storage.ViewSource`.

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
    self._split_of = [self._frame_splits(i) for i in range(len(self.captures))]
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

  def _frame_splits(self, i: int) -> list[str]:
    frames = self.captures[i].frames
    if i in self.unseen:
      return ["test_scenes"] * len(frames)
    if any(f.split is not None for f in frames):
      return [f.split or "train" for f in frames]
    k = self.holdout_every
    return ["test" if k and j % k == 0 else "train" for j in range(len(frames))]

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
          "split_rule": (
            "whole capture held out"
            if i in self.unseen
            else "capture's own split files"
            if any(f.split for f in cap.frames)
            else f"every {self.holdout_every}th view held out"
            if self.holdout_every
            else "every view trains"
          ),
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
