"""Tests of camrep.data.feed.storage: exact round trip through tfds ArrayRecord, and errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camrep.data import prepare, sources
from camrep.data.errors import DataError
from camrep.data.feed import pipeline, storage
from camrep.data.feed.storage import ViewSource
from camrep.data.readers import gqn
from tests import readers_fixtures as fx


class FakeSource:
  """A tiny source: random pixels and poses, uneven view counts, splits train/test/test_scenes."""

  name = "fake"
  pose_names = ("x", "y", "yaw")
  image_size = (6, 10)
  _views = {"train": [3, 5, 4], "test": [2, 2, 1], "test_scenes": [4, 4]}

  def num_scenes(self, split: str) -> int:
    return len(self._views[split])

  def iter_views(self, split: str):
    rng = np.random.default_rng(len(split))
    for scene, n in enumerate(self._views[split]):
      for view in range(n):
        yield {
          "image": rng.integers(0, 256, size=(6, 10, 3), dtype=np.uint8),
          "pose": rng.uniform(0, 6, size=3).astype(np.float32),
          "scene": scene,
          "view": view,
        }


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
  data_dir = tmp_path_factory.mktemp("tfds")
  path = storage.prepare(
    FakeSource(), data_dir, config="tiny", metadata={"why": "test"}, progress=False
  )
  return data_dir, path


def test_fake_source_follows_protocol():
  assert isinstance(FakeSource(), ViewSource)
  assert storage.source_splits(FakeSource()) == ("train", "test", "test_scenes")


def test_png_round_trip_exact():
  img = np.random.default_rng(0).integers(0, 256, size=(7, 5, 3), dtype=np.uint8)
  np.testing.assert_array_equal(storage.decode_png(storage.encode_png(img)), img)


@pytest.mark.parametrize("split", ["train", "test", "test_scenes"])
def test_round_trip_exact(prepared, split):
  data_dir, path = prepared
  assert path == data_dir / "fake" / "tiny" / "1.0.0"
  expected = list(FakeSource().iter_views(split))
  stored = storage.load(data_dir, "fake", split)
  assert len(stored) == len(expected)
  seen = set()
  for rec in stored:
    exp = expected[rec["index"]]
    seen.add(rec["index"])
    np.testing.assert_array_equal(rec["image"], exp["image"])
    assert rec["image"].dtype == np.uint8
    np.testing.assert_array_equal(rec["pose"], exp["pose"])
    assert (rec["scene"], rec["view"]) == (exp["scene"], exp["view"])
  assert seen == set(range(len(expected)))


@pytest.mark.parametrize("split", ["train", "test"])
def test_sidecar_matches_records(prepared, split):
  data_dir, _ = prepared
  stored = storage.load(data_dir, "fake", split, config="tiny", version="1.0.0")
  expected = list(FakeSource().iter_views(split))
  idx = stored.index
  np.testing.assert_array_equal(idx.index, np.arange(len(expected)))
  np.testing.assert_array_equal(idx.scene, [e["scene"] for e in expected])
  np.testing.assert_array_equal(idx.view, [e["view"] for e in expected])
  np.testing.assert_array_equal(idx.pose, np.stack([e["pose"] for e in expected]))
  images = stored.read_images(idx.record.reshape(-1, 1))
  assert images.shape == (len(expected), 1, 6, 10, 3)
  np.testing.assert_array_equal(images[:, 0], np.stack([e["image"] for e in expected]))
  assert idx.pose_names == ("x", "y", "yaw") and idx.image_shape == (6, 10)


def test_metadata(prepared):
  _, path = prepared
  meta = json.loads((path / storage.METADATA_FILE).read_text())
  assert meta["splits"]["train"] == {"num_views": 12, "num_scenes": 3}
  assert meta["splits"]["test_scenes"] == {"num_views": 8, "num_scenes": 2}
  assert meta["image_shape"] == [6, 10] and meta["metadata"] == {"why": "test"}


def test_prepare_again_reuses(prepared):
  data_dir, path = prepared
  again = storage.prepare(FakeSource(), data_dir, config="tiny", progress=False)
  assert again == path


def test_load_errors(prepared, tmp_path):
  data_dir, _ = prepared
  with pytest.raises(DataError, match="does not exist"):
    storage.load(tmp_path / "nope", "fake", "train")
  with pytest.raises(DataError, match="no prepared dataset 'fake'"):
    storage.load(tmp_path, "fake", "train")
  with pytest.raises(DataError, match="unknown split 'val'"):
    storage.load(data_dir, "fake", "val")
  with pytest.raises(DataError, match="no config 'big'"):
    storage.load(data_dir, "fake", "train", config="big")
  with pytest.raises(DataError, match="no version '9.9.9'"):
    storage.load(data_dir, "fake", "train", version="9.9.9")


def test_bad_record_is_named(tmp_path):
  class Broken(FakeSource):
    name = "broken"

    def iter_views(self, split):
      for rec in super().iter_views(split):
        yield {**rec, "image": rec["image"][:, :5]}

  with pytest.raises(DataError, match=r"broken/train #0: image must be uint8"):
    storage.prepare(Broken(), tmp_path, progress=False)


def test_a_split_without_views_is_named_and_nothing_is_kept(tmp_path):
  class Empty(FakeSource):
    name = "empty"
    _views = {**FakeSource._views, "test": [0, 0, 0]}

  with pytest.raises(DataError, match=r"source 'empty' gave no view for its 'test' split"):
    storage.prepare(Empty(), tmp_path, progress=False)
  assert [p.name for p in tmp_path.rglob("*")] == ["empty"]  # the (empty) lock directory


def test_overwrite_regenerates(tmp_path):
  class Shifted(FakeSource):
    def iter_views(self, split):
      for rec in super().iter_views(split):
        yield {**rec, "pose": rec["pose"] + 1}

  storage.prepare(FakeSource(), tmp_path, progress=False)
  path = storage.prepare(Shifted(), tmp_path, overwrite=True, progress=False)
  stored = storage.load(tmp_path, "fake", "test")
  expected = np.stack([r["pose"] for r in Shifted().iter_views("test")])
  np.testing.assert_array_equal(stored.index.pose, expected)
  assert path == tmp_path / "fake" / "1.0.0"


def test_prepare_cli_errors(tmp_path, capsys):
  """Each mistake: exit 2 and one `error:` line (camrep.runtime.cli), nothing written."""
  cases = [
    (["--source", "nope"], "error: --source=nope: value should be one of"),
    (["--source", "gqn"], "error: --source=gqn reads a dataset: give its root with --input PATH"),
    (["--source", "rooms", "--input", str(tmp_path)], "error: --source=rooms is procedural"),
    (["--source", "rooms", "--config.no_such_field=1"], "error: --config.no_such_field=1: the"),
    (["--source", "rooms", "--config.num_train_scenes=x"], "error: --config.num_train_scenes=x"),
    (["--source", "gqn", "--input", str(tmp_path / "x")], "input path does not exist"),
    (["--source", "rooms", "--config.seed"], "error: --config.seed"),
  ]
  for args, message in cases:
    assert prepare.main([*args, "--data_dir", str(tmp_path / "tfds")]) == 2, args
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err, (args, err)
  assert not (tmp_path / "tfds").exists()
  with pytest.raises(DataError, match="unknown data source 'nope'"):
    sources.build("nope")
  with pytest.raises(DataError, match="no preset 'huge'"):
    sources.build("gqn", input_path=tmp_path, preset="huge")


def test_source_fields_are_the_constructors_keywords():
  """`--config.` of prepare: every keyword of each source's constructor (captures' new readers
  get theirs from the same table)."""
  assert prepare.source_fields("gqn")["max_files"] is None
  assert prepare.source_fields("seven_scenes")["extent"] == (4.0, 1.5, 3.0)
  assert prepare.source_fields("rooms")["num_train_scenes"] == 200_000
  for name in sources.SOURCES:
    assert "root" not in prepare.source_fields(name)


def test_prepare_lists_every_registered_source(capsys):
  prepare.main(["--list"])
  listed = [line.split()[0] for line in capsys.readouterr().out.splitlines() if line[:1].strip()]
  assert listed == list(sources.SOURCES)


def test_prepare_cli_real_reader_end_to_end(tmp_path, capsys):
  """gqn: TFRecords -> prepare CLI -> tfds -> pipeline, pixels equal to the reader's."""
  root = tmp_path / "gqn"
  shard = root / gqn.ROOMS / "test"
  shard.mkdir(parents=True)
  rng = np.random.default_rng(0)
  fx.write_gqn_tfrecord(shard / "1-of-1.tfrecord", [fx.gqn_scene(rng, size=16) for _ in range(3)])
  args = ["--source", "gqn", "--input", str(root), "--data_dir", str(tmp_path / "tfds")]
  assert prepare.main([*args, "--config.image_size=16", "--no_progress"]) == 0
  path = tmp_path / "tfds" / "gqn" / storage.DEFAULT_VERSION
  assert f"wrote {path}" in capsys.readouterr().out
  reader = gqn.GQN(root, image_size=16)
  for split in ("train", "test"):
    expected = list(reader.iter_views(split))
    stored = storage.load(tmp_path / "tfds", "gqn", split)
    assert len(stored) == len(expected) == 3 * (9 if split == "train" else 1)
    for rec in stored:
      exp = expected[rec["index"]]
      np.testing.assert_array_equal(rec["image"], exp["image"])
      np.testing.assert_array_equal(rec["pose"], exp["pose"])
  cfg = pipeline.PipelineConfig(scenes_per_device=3, views_per_scene=9)
  batch = pipeline.tfds_pipeline(tmp_path / "tfds", "gqn", "train", cfg).batch(0)
  assert batch["image"].shape == (1, 3, 9, 16, 16, 3)
  assert sorted(batch["view"][0, 0].tolist()) == list(range(9))
  # Same settings again: reused. Other settings into the same directory: refused.
  assert prepare.main([*args, "--config.image_size=16", "--no_progress"]) == 0
  assert "reused" in capsys.readouterr().out
  assert prepare.main([*args, "--config.image_size=16", "--config.max_scenes=2"]) == 2
  assert "already prepared with" in capsys.readouterr().err
