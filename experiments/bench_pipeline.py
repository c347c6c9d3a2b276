"""Benchmark: time to prepare a tfds dataset, and pipeline batches/s and images/s.

Prepares a small GQN-rooms-like dataset (the procedural "rooms" family, rendered; or with
`--source stand_in` a built-in source of smooth 64 px images that needs no rendering) into a
temporary data_dir, then reads batches laid out like the GQN train step
(8 scenes x 9 views of 64 px by default) in several ways:

  memory      the same `BatchPipeline` over images already in RAM (batching code alone)
  tfds        `tfds_pipeline(...).batch(k)` in the caller's thread (PNG decoding included)
  grain       `tfds_pipeline(...).iterator()`, grain MapDataset + reader threads, no worker
              processes (`data.num_workers=0`)
  workers=N   the same iterator with N worker processes (`data.num_workers=N`, grain
              `mp_prefetch`; each with `--threads` reader threads), for each N of `--workers`
  +device     the last of those, followed by `pipeline.prefetch_to_device` (2 batches ahead, as
              the train loop does): batches arrive as device arrays
  dataloader  the same steps through `grain.DataLoader` (IndexSampler, worker_count=0)

Worker processes are started before the timing (the first, warm-up batch waits for them); the
line `workers: N (default for this machine's C usable cores: M)` gives the config's default.

Command (about 30 s on a 2-core CPU; no accelerator needed):

  .venv/bin/python experiments/bench_pipeline.py [--source rooms|stand_in] [--scenes 64]
      [--views 10] [--size 64] [--scenes_per_device 8] [--views_per_scene 9] [--steps 30]
      [--threads 2] [--workers 2]

On a 16-core GPU machine, the paper's batch layout (30 scenes x 9 views) against worker counts:

  python experiments/bench_pipeline.py --scenes 256 --scenes_per_device 30 --views_per_scene 9 \
      --steps 60 --workers 4,8,14
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections.abc import Iterator

import cv2
import grain
import jax
import numpy as np

from camrep.data import pipeline, procedural, storage


class StandInRooms:
  """A GQN-rooms-like stand-in: x, y in [-1, 1], yaw in [0, 2 pi); smooth 'wall' images."""

  name = "bench_rooms"
  pose_names = ("x", "y", "yaw")

  def __init__(self, num_scenes: int, views: int, size: int):
    self.image_size = size
    self._scenes = {"train": num_scenes}
    self._views = views

  def num_scenes(self, split: str) -> int:
    return self._scenes[split]

  def iter_views(self, split: str) -> Iterator[dict]:
    rng = np.random.default_rng(0)
    s = self.image_size
    u = np.linspace(0, 1, s, dtype=np.float32)
    for scene in range(self._scenes[split]):
      colours = rng.uniform(30, 230, size=(4, 3)).astype(np.float32)
      for view in range(self._views):
        x, y = rng.uniform(-1, 1, size=2)
        yaw = rng.uniform(0, 2 * np.pi)
        wall = int(yaw / (np.pi / 2)) % 4
        shade = 0.6 + 0.4 * np.cos(yaw + 6 * u)[None, :, None]
        image = np.empty((s, s, 3), np.float32)
        image[: s // 2] = colours[wall] * shade
        image[s // 2 :] = colours[(wall + 2) % 4] * (0.5 + 0.5 * u[s // 2 :, None, None])
        cv2.circle(
          image, (int(s * (0.5 + 0.3 * x)), int(s * (0.6 + 0.2 * y))), s // 8, (250, 80, 40), -1
        )
        yield {
          "image": np.clip(image, 0, 255).astype(np.uint8),
          "pose": np.array([x, y, yaw], np.float32),
          "scene": scene,
          "view": view,
        }


def make_source(
  kind: str, num_scenes: int, views: int, size: int
) -> tuple[storage.ViewSource, str]:
  """The procedural rooms family ("rooms") or the cheap stand-in ("stand_in")."""
  if kind == "stand_in":
    return StandInRooms(num_scenes, views, size), "stand-in rooms (no rendering)"
  family = procedural.make_family(
    "rooms",
    image_size=size,
    num_train_scenes=num_scenes,
    train_views=views,
    num_test_scenes=1,
    test_views=1,
  )
  return family, "procedural rooms (camrep.data.procedural)"


def time_batches(batches: Iterator[dict], steps: int) -> float:
  """Seconds to pull `steps` batches, after one warm-up batch."""
  next(batches)
  t0 = time.perf_counter()
  for _ in range(steps):
    next(batches)
  return time.perf_counter() - t0


class _Steps:
  """Random-access view of a pipeline's steps, for grain.DataLoader."""

  def __init__(self, pipe: pipeline.BatchPipeline, num_steps: int):
    self._pipe, self._n = pipe, num_steps

  def __len__(self) -> int:
    return self._n

  def __getitem__(self, step: int) -> dict:
    return self._pipe.batch(int(step))


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--source", default="rooms", choices=("rooms", "stand_in"))
  parser.add_argument("--scenes", type=int, default=64)
  parser.add_argument("--views", type=int, default=10)
  parser.add_argument("--size", type=int, default=64)
  parser.add_argument("--scenes_per_device", type=int, default=8)
  parser.add_argument("--views_per_scene", type=int, default=9)
  parser.add_argument("--num_devices", type=int, default=1)
  parser.add_argument("--mode", default="random", choices=pipeline.MODES)
  parser.add_argument("--steps", type=int, default=30)
  parser.add_argument("--threads", type=int, default=2)
  parser.add_argument(
    "--workers", default="2", help="comma-separated worker-process counts to time (0: skip)"
  )
  args = parser.parse_args()

  source, kind = make_source(args.source, args.scenes, args.views, args.size)
  cfg = pipeline.PipelineConfig(
    num_devices=args.num_devices,
    scenes_per_device=args.scenes_per_device,
    views_per_scene=args.views_per_scene,
    mode=args.mode,
    num_threads=args.threads,
  )
  images_per_batch = cfg.scenes_per_step * cfg.views_per_scene
  print(f"source: {kind}; {args.scenes} scenes x {args.views} views of {args.size} px")
  print(
    f"layout: {cfg.num_devices} x {cfg.scenes_per_device} scenes x {cfg.views_per_scene} "
    f"views ({images_per_batch} images/batch), mode {cfg.mode}"
  )

  with tempfile.TemporaryDirectory() as data_dir:
    t0 = time.perf_counter()
    path = storage.prepare(source, data_dir, progress=False)
    prep = time.perf_counter() - t0
    n = storage.load_metadata(path)["splits"]["train"]["num_views"]
    size_mb = sum(f.stat().st_size for f in path.iterdir()) / 2**20
    print(f"prepare: {prep:.2f} s for {n} views ({n / prep:.0f} views/s, {size_mb:.1f} MiB)")

    t0 = time.perf_counter()
    stored = pipeline.tfds_pipeline(data_dir, source.name, "train", cfg)
    print(f"open tfds pipeline: {time.perf_counter() - t0:.2f} s")
    # The in-memory variant over the same views, loaded from the store (not re-rendered).
    images = storage.load(data_dir, source.name, "train").read_images(np.arange(n))
    memory = pipeline.BatchPipeline(stored.index, lambda records: images[records], cfg)
    workers = [int(w) for w in args.workers.split(",") if int(w) > 0]
    cores = pipeline.usable_cores()
    print(
      f"workers: {workers} (default for this machine's {cores} usable cores: "
      f"{pipeline.default_num_workers(cores)})"
    )

    def with_workers(w: int):
      return pipeline.tfds_pipeline(
        data_dir, source.name, "train", dataclasses.replace(cfg, num_workers=w)
      ).iterator()

    # Each iterator is made just before it is timed and closed after, so no worker processes
    # run during another row's timing.
    runs = {
      "memory": lambda: (memory.batch(k) for k in range(10**9)),
      "tfds": lambda: (stored.batch(k) for k in range(10**9)),
      "grain": stored.iterator,
      **{f"workers={w}": (lambda w=w: with_workers(w)) for w in workers},
      "dataloader": lambda: iter(
        grain.DataLoader(
          data_source=_Steps(stored, args.steps + 1),
          sampler=grain.samplers.IndexSampler(args.steps + 1, shuffle=False, num_epochs=1),
          worker_count=0,
          read_options=grain.ReadOptions(num_threads=args.threads, prefetch_buffer_size=4),
        )
      ),
    }
    if workers:
      runs[f"workers={workers[-1]}+device"] = lambda: with_workers(workers[-1])
    for label, make_batches in runs.items():
      host = make_batches()
      batches = host
      if label.endswith("+device"):
        batches = (jax.block_until_ready(b) for b in pipeline.prefetch_to_device(host, 2))
      dt = time_batches(batches, args.steps)
      print(
        f"{label:>18}: {args.steps / dt:8.1f} batches/s  "
        f"{args.steps * images_per_batch / dt:9.0f} images/s",
        flush=True,
      )
      if hasattr(host, "close"):
        host.close()


if __name__ == "__main__":
  main()
