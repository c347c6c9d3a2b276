"""Tests for the real-dataset readers: 7-Scenes, GQN TFRecords, SRN cars and Gibson rooms.

7-Scenes is tested on the real stairs sample in shared/fixtures (read-only; copied to tmp_path
before being damaged); the other datasets on fixtures written in their exact on-disk formats by
`tests/readers_fixtures.py`. scipy's `Rotation` is the oracle for the 6-DOF conversions.
"""

from __future__ import annotations

import logging
import os
import pathlib
import pickle
import shutil

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from camrep.data import sources
from camrep.data.errors import DataError
from camrep.data.readers import gibson, gqn, imageio, seven_scenes, srn
from camrep.data.records import RECORD_KEYS
from tests import readers_fixtures as fx

_REPO = pathlib.Path(__file__).resolve().parents[1]
_SHARED = pathlib.Path(os.environ.get("CAMREP_SHARED", _REPO.parent / "shared"))
STAIRS = _SHARED / "fixtures" / "7scenes_stairs_sample" / "stairs"
POSE_TABLES = _SHARED / "data" / "7scenes_poses"

needs_stairs = pytest.mark.skipif(
  not STAIRS.is_dir(), reason=f"real 7-Scenes sample not at {STAIRS}"
)
needs_tables = pytest.mark.skipif(
  not POSE_TABLES.is_dir(), reason=f"7-Scenes pose tables not at {POSE_TABLES}"
)


def _check_records(records, *, pose_dim, image_size, num_scenes=None):
  """Asserts the view-record contract of camrep/data/records.py on a list of records."""
  assert records, "no records"
  seen = {}
  for r in records:
    assert tuple(sorted(r)) == tuple(sorted(RECORD_KEYS))
    assert r["image"].dtype == np.uint8 and r["image"].shape == (image_size, image_size, 3)
    assert r["pose"].dtype == np.float32 and r["pose"].shape == (pose_dim,)
    assert np.all(np.isfinite(r["pose"]))
    assert isinstance(r["scene"], int) and isinstance(r["view"], int)
    seen.setdefault(r["scene"], []).append(r["view"])
  for views in seen.values():
    assert views == list(range(len(views)))
  if num_scenes is not None:
    assert sorted(seen) == list(range(num_scenes))


def _random_rotations(n, seed=0):
  return Rotation.random(n, random_state=seed).as_matrix()


# ---------------------------------------------------------------------------------------------
# imageio


def test_decode_image_rgb_order_gray_and_alpha(tmp_path):
  bgr = np.zeros((4, 6, 3), np.uint8)
  bgr[..., 0] = 10  # blue
  bgr[..., 2] = 200  # red
  ok, png = cv2.imencode(".png", bgr)
  assert ok
  rgb = imageio.decode_image(png.tobytes(), "x.png")
  assert rgb.shape == (4, 6, 3) and rgb[0, 0].tolist() == [200, 0, 10]
  bgra = np.concatenate([bgr, np.full((4, 6, 1), 7, np.uint8)], axis=2)
  rgb = imageio.decode_image(cv2.imencode(".png", bgra)[1].tobytes(), "x.png")
  assert rgb.shape == (4, 6, 3) and rgb[0, 0].tolist() == [200, 0, 10]
  gray = imageio.decode_image(cv2.imencode(".png", bgr[..., 2])[1].tobytes(), "x.png")
  assert gray.shape == (4, 6, 3) and gray[0, 0].tolist() == [200, 200, 200]


def test_decode_image_errors_name_the_file(tmp_path):
  with pytest.raises(DataError, match="bad.png: cannot decode"):
    imageio.decode_image(b"\x89PNG not really", "bad.png")
  with pytest.raises(DataError, match="cannot decode"):
    imageio.decode_image(b"", "empty.png")
  with pytest.raises(DataError, match="missing.png: cannot read"):
    imageio.read_image(tmp_path / "missing.png")
  p = tmp_path / "deep.png"
  cv2.imwrite(str(p), np.zeros((3, 3, 3), np.uint16))
  with pytest.raises(DataError, match="8-bit"):
    imageio.read_image(p)
  p = tmp_path / "small.png"
  cv2.imwrite(str(p), np.zeros((3, 5, 3), np.uint8))
  with pytest.raises(DataError, match="small.png: image is 3x5 .* expected 4x4"):
    imageio.read_image(p, expected_hw=(4, 4))


def test_crop_and_resize_is_centre_crop_then_inter_area():
  rng = np.random.default_rng(0)
  img = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
  out = imageio.crop_and_resize(img, 16)
  want = cv2.resize(img[:, 8:56], (16, 16), interpolation=cv2.INTER_AREA)
  np.testing.assert_array_equal(out, want)
  np.testing.assert_array_equal(imageio.crop_and_resize(img[:48, :48], 48), img[:48, :48])


# ---------------------------------------------------------------------------------------------
# 7-Scenes: pose conversion (scipy oracle)


def test_euler_matches_scipy_and_transforms3d_convention():
  rot = _random_rotations(200)
  ours = seven_scenes.matrix_to_euler_sxyz(rot)
  np.testing.assert_allclose(ours, Rotation.from_matrix(rot).as_euler("xyz"), atol=1e-10)
  # Static axes: R = Rz(psi) Ry(phi) Rx(theta).
  theta, phi, psi = ours[7]
  rz, ry, rx = (
    Rotation.from_euler(a, v).as_matrix() for a, v in zip("zyx", (psi, phi, theta), strict=True)
  )
  np.testing.assert_allclose(rz @ ry @ rx, rot[7], atol=1e-12)
  np.testing.assert_allclose(seven_scenes.euler_sxyz_to_matrix(ours), rot, atol=1e-12)


def test_euler_gimbal_lock_follows_transforms3d():
  # phi = +-pi/2: transforms3d sets psi = 0 and puts the whole in-plane angle into theta.
  for phi in (np.pi / 2, -np.pi / 2):
    rot = seven_scenes.euler_sxyz_to_matrix(np.array([0.3, phi, 0.5]))
    ang = seven_scenes.matrix_to_euler_sxyz(rot)
    assert ang[2] == 0.0 and abs(abs(ang[1]) - np.pi / 2) < 1e-7
    np.testing.assert_allclose(seven_scenes.euler_sxyz_to_matrix(ang), rot, atol=1e-7)


def test_c2w_dofs_round_trip_and_ranges():
  n = 64
  rng = np.random.default_rng(1)
  poses = np.tile(np.eye(4), (n, 1, 1))
  poses[:, :3, :3] = _random_rotations(n, seed=1)
  poses[:, :3, 3] = rng.uniform(-2, 2, (n, 3))
  t_min = seven_scenes.translation_min(poses)
  np.testing.assert_array_equal(t_min, poses[:, :3, 3].min(0))
  dofs = seven_scenes.c2w_to_dofs(poses, t_min)
  assert dofs.shape == (n, 6) and dofs.dtype == np.float64
  assert np.all(dofs[:, :3] >= 0) and np.all(dofs[:, :3].min(0) == 0)
  assert np.all((dofs[:, 3] >= 0) & (dofs[:, 3] <= 2 * np.pi))
  assert np.all((dofs[:, 4] >= 0) & (dofs[:, 4] <= np.pi))
  assert np.all((dofs[:, 5] >= 0) & (dofs[:, 5] <= 2 * np.pi))
  want = Rotation.from_matrix(poses[:, :3, :3]).as_euler("xyz") + [np.pi, np.pi / 2, np.pi]
  np.testing.assert_allclose(dofs[:, 3:], want, atol=1e-10)
  np.testing.assert_allclose(seven_scenes.dofs_to_c2w(dofs, t_min), poses, atol=1e-12)


def test_c2w_to_dofs_orthonormalises_rotation():
  rot = _random_rotations(5, seed=2)
  noisy = rot + 1e-4 * np.random.default_rng(2).standard_normal(rot.shape)
  proj = seven_scenes.orthonormalize(noisy)
  np.testing.assert_allclose(
    proj @ np.swapaxes(proj, 1, 2), np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-12
  )
  np.testing.assert_allclose(np.linalg.det(proj), 1.0, atol=1e-12)
  np.testing.assert_allclose(proj, rot, atol=1e-3)
  # A reflection is projected to a proper rotation, not kept.
  assert np.linalg.det(seven_scenes.orthonormalize(np.diag([1.0, 1.0, -1.0]))) > 0
  poses = np.tile(np.eye(4), (5, 1, 1))
  poses[:, :3, :3] = noisy
  dofs = seven_scenes.c2w_to_dofs(poses, np.zeros(3))
  np.testing.assert_allclose(
    seven_scenes.dofs_to_c2w(dofs, np.zeros(3))[:, :3, :3], proj, atol=1e-12
  )


def test_read_pose_table_is_world_to_camera_with_w_first(tmp_path):
  rot_c2w = _random_rotations(3, seed=3)
  centres = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0], [0.0, 0.0, -4.0]])
  lines = ["# comment", ""]
  for i, (r, c) in enumerate(zip(rot_c2w, centres, strict=True)):
    r_w2c = r.T
    t = -r_w2c @ c
    x, y, z, w = Rotation.from_matrix(r_w2c).as_quat()  # scipy is scalar-last
    s = 1.7 if i == 1 else 1.0  # unnormalised quaternions are normalised
    vals = [w * s, x * s, y * s, z * s, *t]
    lines.append(
      f"seq-0{i}/frame-00000{i}.color.png " + " ".join(f"{v:.9f}" for v in vals) + " 525.0"
    )
  path = tmp_path / "scene_train.txt"
  path.write_text("\n".join(lines) + "\n")
  names, poses = seven_scenes.read_pose_table(path)
  assert names == [
    "seq-00/frame-000000.color.png",
    "seq-01/frame-000001.color.png",
    "seq-02/frame-000002.color.png",
  ]
  assert poses.shape == (3, 4, 4) and poses.dtype == np.float64
  np.testing.assert_allclose(poses[:, :3, :3], rot_c2w, atol=1e-8)
  np.testing.assert_allclose(poses[:, :3, 3], centres, atol=1e-8)
  np.testing.assert_array_equal(poses[:, 3], np.broadcast_to([0, 0, 0, 1.0], (3, 4)))


def test_read_pose_table_errors(tmp_path):
  with pytest.raises(DataError, match="nope.txt: cannot read"):
    seven_scenes.read_pose_table(tmp_path / "nope.txt")
  bad = tmp_path / "bad.txt"
  bad.write_text("seq-01/frame-000000.color.png 1 0 0 0 1 2\n")
  with pytest.raises(DataError, match="bad.txt: line 1"):
    seven_scenes.read_pose_table(bad)
  bad.write_text("seq-01/frame-000000.color.png 1 0 0 0 nan 2 3 525\n")
  with pytest.raises(DataError, match="non-finite"):
    seven_scenes.read_pose_table(bad)
  bad.write_text("# only a comment\n")
  with pytest.raises(DataError, match="no rows"):
    seven_scenes.read_pose_table(bad)


@needs_stairs
@needs_tables
def test_pose_table_agrees_with_raw_pose_files():
  # The D-SLAM tables re-optimise the KinectFusion poses: same world frame, within a few cm.
  for split in ("train", "test"):
    data = seven_scenes.read_split(STAIRS, split)
    names, table = seven_scenes.read_pose_table(POSE_TABLES / f"stairs_{split}.txt")
    index = {n: i for i, n in enumerate(names)}
    for path, pose in zip(data["image_paths"], data["poses_c2w"], strict=True):
      other = table[index["/".join(pathlib.Path(path).parts[-2:])]]
      assert np.abs(other[:3, 3] - pose[:3, 3]).max() < 0.05
      assert np.abs(other[:3, :3] - pose[:3, :3]).max() < 0.02


def test_packed_pose_tables_ship_with_the_package():
  names, c2w = seven_scenes.packed_pose_table("stairs", "test")
  assert len(names) == 1000 and c2w.shape == (1000, 4, 4)
  assert names[0].startswith("seq-") and names[0].endswith(".color.png")
  np.testing.assert_allclose(
    c2w[:, :3, :3] @ c2w[:, :3, :3].transpose(0, 2, 1),
    np.broadcast_to(np.eye(3), (1000, 3, 3)),
    atol=1e-5,
  )
  with pytest.raises(DataError, match="no pose table 'attic_test'"):
    seven_scenes.packed_pose_table("attic", "test")


@needs_tables
def test_packed_pose_tables_equal_the_text_tables(tmp_path):
  # Exact: the text has 6 decimals and the file stores integers of 1e-6.
  for path in sorted(POSE_TABLES.glob("*_t*.txt")):
    scene, split = path.stem.rsplit("_", 1)
    names, c2w = seven_scenes.read_pose_table(path)
    packed_names, packed = seven_scenes.packed_pose_table(scene, split)
    assert packed_names == names
    np.testing.assert_array_equal(packed, c2w)
  # Packing again gives the shipped content.
  out = tmp_path / "poses.npz"
  counts = seven_scenes.pack_pose_tables(POSE_TABLES, out)
  assert counts["stairs_train"] == 2000 and len(counts) == 14
  with np.load(out) as a, np.load(seven_scenes.PACKED_POSES) as b:
    assert sorted(a.files) == sorted(b.files)
    for k in a.files:
      np.testing.assert_array_equal(a[k], b[k])


def test_pack_pose_tables_refuses_what_it_cannot_store_exactly(tmp_path):
  line = "seq-01/frame-000001.color.png 1.0 0.0 0.0 0.0 0.1234567 0.0 0.0 525.0\n"
  (tmp_path / "x_train.txt").write_text(line)
  with pytest.raises(DataError, match="more than 6 decimals"):
    seven_scenes.pack_pose_tables(tmp_path, tmp_path / "out.npz")
  (tmp_path / "x_train.txt").write_text(
    line.replace("seq-01/frame-000001", "img1").replace("0.1234567", "0.1")
  )
  with pytest.raises(DataError, match="frame name"):
    seven_scenes.pack_pose_tables(tmp_path, tmp_path / "out.npz")


def test_scene6dof_reads_text_tables_when_told(tmp_path, monkeypatch):
  from camrep.data import procedural

  names, c2w = seven_scenes.packed_pose_table("heads", "train")
  assert procedural.default_pose_dir() is None or "CAMREP_7SCENES_POSES" in os.environ
  monkeypatch.setenv("CAMREP_7SCENES_POSES", str(tmp_path))
  assert procedural.default_pose_dir() == str(tmp_path)
  fam = procedural.make_family("scene6dof", preset="small", scenes=("heads",))
  with pytest.raises(DataError, match="heads_train.txt"):
    fam.poses("train", 0)


# ---------------------------------------------------------------------------------------------
# 7-Scenes: raw layout on the real stairs sample


@needs_stairs
def test_read_split_real_sample_order_and_crlf():
  assert (STAIRS / "TrainSplit.txt").read_bytes().endswith(b"\r\n")
  assert seven_scenes.read_split_file(STAIRS / "TrainSplit.txt") == [2, 3, 5, 6]
  assert seven_scenes.read_split_file(STAIRS / "TestSplit.txt") == [1, 4]
  train = seven_scenes.read_split(STAIRS, "train")
  rel = ["/".join(pathlib.Path(p).parts[-2:]) for p in train["image_paths"]]
  assert rel == [f"seq-{s:02d}/frame-{f:06d}.color.png" for s in (2, 3, 5, 6) for f in range(3)]
  assert train["poses_c2w"].shape == (12, 4, 4) and train["poses_c2w"].dtype == np.float64
  first = np.loadtxt(STAIRS / "seq-02" / "frame-000000.pose.txt")
  np.testing.assert_array_equal(train["poses_c2w"][0], first)
  test = seven_scenes.read_split(STAIRS, "test")
  assert len(test["image_paths"]) == 6 and "seq-01" in test["image_paths"][0]


@needs_stairs
def test_seven_scenes_reader_real_sample(caplog):
  reader = seven_scenes.SevenScenes(STAIRS.parent, image_size=32, margin=0.0)
  assert reader.scenes == ["stairs"] and reader.num_scenes("train") == 1
  assert reader.name == "seven_scenes"
  assert reader.pose_names == sources.get("seven_scenes").pose_names
  records = list(reader.iter_views("train"))
  _check_records(records, pose_dim=6, image_size=32, num_scenes=1)
  assert len(records) == 12
  train = seven_scenes.read_split(STAIRS, "train")
  t_min = seven_scenes.translation_min(train["poses_c2w"])
  want = seven_scenes.c2w_to_dofs(train["poses_c2w"], t_min)
  np.testing.assert_allclose(np.stack([r["pose"] for r in records]), want, rtol=1e-6, atol=1e-6)
  img = imageio.read_image(train["image_paths"][0])
  np.testing.assert_array_equal(
    records[0]["image"], cv2.resize(img[:, 80:560], (32, 32), interpolation=cv2.INTER_AREA)
  )
  # The real stairs test frames start 0.10 m below the TRAINING minimum in x: the strict check
  # refuses them, naming the frame; warn_only or a margin lets them through.
  with pytest.raises(DataError, match=r"seq-01/frame-000000\.pose\.txt: re-based translation"):
    list(reader.iter_views("test"))
  lenient = seven_scenes.SevenScenes(STAIRS.parent, image_size=32, margin=0.0, warn_only=True)
  with caplog.at_level(logging.WARNING):
    records = list(lenient.iter_views("test"))
  assert len(records) == 6 and "outside the grid cuboid" in caplog.text
  margin = seven_scenes.SevenScenes(STAIRS.parent, image_size=32, margin=0.5)
  assert len(list(margin.iter_views("test"))) == 6
  # The default: seven_scenes.DEFAULT_MARGIN admits the real test frames.
  default = seven_scenes.SevenScenes(STAIRS.parent, image_size=32)
  assert default.margin == seven_scenes.DEFAULT_MARGIN == 0.5
  assert len(list(default.iter_views("test"))) == 6


def test_check_pose_range():
  dofs = np.array([[0.0, 0.0, 0.0, 1, 1, 1], [4.0, 1.5, 3.0, 1, 1, 1], [1.0, 1.6, 1.0, 1, 1, 1]])
  files = ["a.pose.txt", "b.pose.txt", "c.pose.txt"]
  assert seven_scenes.check_pose_range(dofs[:2], files) == 0
  with pytest.raises(DataError, match="c.pose.txt: re-based translation"):
    seven_scenes.check_pose_range(dofs, files)
  assert seven_scenes.check_pose_range(dofs, files, warn_only=True) == 1
  assert seven_scenes.check_pose_range(dofs, files, margin=0.2) == 0
  dofs[0, 4] = np.inf
  with pytest.raises(DataError, match="a.pose.txt: non-finite pose"):
    seven_scenes.check_pose_range(dofs, files, warn_only=True)


@pytest.fixture
def stairs_copy(tmp_path):
  if not STAIRS.is_dir():
    pytest.skip(f"real 7-Scenes sample not at {STAIRS}")
  dst = tmp_path / "7scenes" / "stairs"
  shutil.copytree(STAIRS, dst)
  return dst


def test_seven_scenes_bad_inputs(stairs_copy, tmp_path):
  frame = stairs_copy / "seq-03" / "frame-000001"
  reader = seven_scenes.SevenScenes(stairs_copy.parent, image_size=16, margin=1.0)
  # Non-finite pose.
  good_pose = pathlib.Path(f"{frame}.pose.txt").read_text()
  pathlib.Path(f"{frame}.pose.txt").write_text(good_pose.replace("1.0000000e+000", "nan", 1))
  with pytest.raises(DataError, match=r"seq-03/frame-000001\.pose\.txt: non-finite pose"):
    list(reader.iter_views("train"))
  # Malformed pose.
  pathlib.Path(f"{frame}.pose.txt").write_text("1 2 3\r\n")
  with pytest.raises(DataError, match=r"frame-000001\.pose\.txt: expected 16 numbers"):
    seven_scenes.read_split(stairs_copy, "train")
  pathlib.Path(f"{frame}.pose.txt").write_text(good_pose)
  # Wrong image size.
  cv2.imwrite(f"{frame}.color.png", np.zeros((240, 320, 3), np.uint8))
  with pytest.raises(DataError, match=r"frame-000001\.color\.png: image is 240x320 .* 480x640"):
    list(reader.iter_views("train"))
  # Undecodable image.
  pathlib.Path(f"{frame}.color.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
  with pytest.raises(DataError, match=r"frame-000001\.color\.png: cannot decode"):
    list(reader.iter_views("train"))
  # Missing pose file, missing sequence, empty sequence, bad split line, missing dirs.
  os.remove(f"{frame}.pose.txt")
  with pytest.raises(DataError, match="pose file missing"):
    seven_scenes.read_split(stairs_copy, "train")
  pathlib.Path(f"{frame}.pose.txt").write_text(good_pose)
  shutil.rmtree(stairs_copy / "seq-05")
  with pytest.raises(DataError, match="seq-05: sequence 5 listed in TrainSplit.txt is missing"):
    seven_scenes.read_split(stairs_copy, "train")
  for f in (stairs_copy / "seq-04").iterdir():
    f.unlink()
  with pytest.raises(DataError, match="seq-04: sequence directory holds no"):
    seven_scenes.read_split(stairs_copy, "test")
  (stairs_copy / "TestSplit.txt").write_bytes(b"sequence1\r\nseq 4\r\n")
  with pytest.raises(DataError, match=r"TestSplit.txt: line 2: expected 'sequenceK'"):
    seven_scenes.read_split(stairs_copy, "test")
  (stairs_copy / "TestSplit.txt").write_bytes(b"# nothing\r\n\r\n")
  with pytest.raises(DataError, match="lists no sequences"):
    seven_scenes.read_split(stairs_copy, "test")
  with pytest.raises(DataError, match="does not exist"):
    seven_scenes.SevenScenes(tmp_path / "absent")
  (tmp_path / "empty").mkdir()
  with pytest.raises(DataError, match="empty: no scene directory"):
    seven_scenes.SevenScenes(tmp_path / "empty")
  with pytest.raises(ValueError, match="split"):
    reader.num_scenes("val")


# ---------------------------------------------------------------------------------------------
# GQN TFRecords


def _gqn_root(tmp_path, scenes_per_file=(2, 1), *, size=64, seed=0):
  rng = np.random.default_rng(seed)
  d = tmp_path / "gqn" / gqn.ROOMS / "test"
  d.mkdir(parents=True)
  written = []
  for k, n in enumerate(scenes_per_file, start=1):
    scenes = [fx.gqn_scene(rng, size=size) for _ in range(n)]
    fx.write_gqn_tfrecord(d / f"{k:03d}-of-240.tfrecord", scenes)
    written.extend(scenes)
  return tmp_path / "gqn", d, written


def test_masked_crc_matches_tfrecord_writer():
  for data in (b"", b"abc", bytes(range(256)) * 3):
    assert gqn.masked_crc32c(data).to_bytes(4, "little") == fx.TFRecordWriter.masked_crc(data)


def test_read_tfrecord_round_trip(tmp_path):
  _, d, written = _gqn_root(tmp_path, (3,))
  scenes = list(gqn.read_tfrecord(d / "001-of-240.tfrecord", frame_size=64))
  assert len(scenes) == 3 and gqn.count_records(d / "001-of-240.tfrecord") == 3
  for got, (frames, cameras) in zip(scenes, written, strict=True):
    assert got["frames"].dtype == np.uint8 and got["frames"].shape == (10, 64, 64, 3)
    assert got["cameras"].dtype == np.float32 and got["cameras"].shape == (10, 5)
    np.testing.assert_array_equal(got["cameras"], cameras)
    # JPEG is lossy: compare with a tolerance, and check the channel order is RGB.
    err = np.abs(got["frames"].astype(int) - frames.astype(int))
    assert err.mean() < 4
    swapped = np.abs(got["frames"][..., ::-1].astype(int) - frames.astype(int)).mean()
    assert swapped > 2 * err.mean()


def test_gqn_file_listing(tmp_path):
  root, d, _ = _gqn_root(tmp_path, (1, 1, 1))
  (d / "notes.txt").write_text("ignored: not a .tfrecord")
  files = gqn.list_tfrecords(root, gqn.ROOMS, "test")
  assert [os.path.basename(f) for f in files] == [f"00{k}-of-240.tfrecord" for k in (1, 2, 3)]
  with pytest.raises(DataError, match=r"train: GQN split directory does not exist"):
    gqn.list_tfrecords(root, gqn.ROOMS, "train")
  (root / gqn.ROOMS / "train").mkdir()
  with pytest.raises(DataError, match=r"train: no NNN-of-MMM.tfrecord files"):
    gqn.list_tfrecords(root, gqn.ROOMS, "train")
  (d / "0-of-240.tfrecord").write_bytes(b"")
  with pytest.raises(DataError, match=r"0-of-240.tfrecord: file number must be 1-based"):
    gqn.list_tfrecords(root, gqn.ROOMS, "test")
  os.remove(d / "0-of-240.tfrecord")
  (d / "004-of-241.tfrecord").write_bytes(b"")
  with pytest.raises(DataError, match="disagree on the number of shards"):
    gqn.list_tfrecords(root, gqn.ROOMS, "test")


def test_gqn_reader_splits_and_poses(tmp_path):
  root, _, written = _gqn_root(tmp_path, (2, 1))
  reader = gqn.GQN(root)
  assert reader.name == "gqn" and reader.pose_names == ("x", "y", "yaw")
  assert reader.num_scenes("train") == reader.num_scenes("test") == 3
  train, test = list(reader.iter_views("train")), list(reader.iter_views("test"))
  assert len(train) == 27 and len(test) == 3
  _check_records(train, pose_dim=3, image_size=64, num_scenes=3)
  assert [r["view"] for r in test] == [9, 9, 9] and [r["scene"] for r in test] == [0, 1, 2]
  for r in test:
    assert r["image"].shape == (64, 64, 3) and r["pose"].dtype == np.float32
  cameras = written[1][1]
  np.testing.assert_allclose(train[9 + 4]["pose"][:2], cameras[4, :2])
  np.testing.assert_allclose(train[9 + 4]["pose"][2], np.mod(cameras[4, 3], 2 * np.pi), rtol=1e-6)
  assert all(0 <= r["pose"][2] < 2 * np.pi for r in train + test)
  assert gqn.GQN(root, max_scenes=2).num_scenes("test") == 2
  assert len(list(gqn.GQN(root, max_files=1).iter_views("test"))) == 2


def test_gqn_yaw_wrap_and_range():
  cams = np.array([[0, 0, 0, -2 * np.pi, 0], [0, 0, 0, -1e-9, 0], [0, 0, 0, 7.0, 0]], np.float32)
  poses = gqn.cameras_to_poses(cams)
  assert poses.dtype == np.float32
  assert np.all((poses[:, 2] >= 0) & (poses[:, 2] < np.float32(2 * np.pi)))
  np.testing.assert_allclose(poses[2, 2], 7.0 - 2 * np.pi, rtol=1e-5)
  gqn.check_xy_range(np.array([[-1.0, 1.09, 0.0]]), "f.tfrecord", 0)
  with pytest.raises(DataError, match=r"f.tfrecord: record 3, view 0: position .* outside"):
    gqn.check_xy_range(np.array([[1.1, 0.0, 0.0]]), "f.tfrecord", 3)
  gqn.check_xy_range(np.array([[1.1, 0.0, 0.0]]), "f.tfrecord", 3, xy_range=(-2, 2))


def test_gqn_truncated_and_corrupt_files(tmp_path):
  _, d, _ = _gqn_root(tmp_path, (3,))
  good = (d / "001-of-240.tfrecord").read_bytes()
  first_len = int.from_bytes(good[:8], "little")
  second = 12 + first_len + 4
  bad = tmp_path / "bad.tfrecord"
  cases = {
    good[: second + 5]: r"bad.tfrecord: record 1: truncated header",
    good[: second + 40]: r"bad.tfrecord: record 1: truncated payload",
    good[:-2]: r"bad.tfrecord: record 2: truncated data CRC",
    good[:second] + b"\xff" + good[second + 1 :]: r"bad.tfrecord: record 1: length CRC mismatch",
    good[:100] + bytes([good[100] ^ 1]) + good[101:]: r"bad.tfrecord: record 0: data CRC mismatch",
  }
  for data, msg in cases.items():
    bad.write_bytes(data)
    with pytest.raises(DataError, match=msg):
      list(gqn.read_tfrecord(bad))
  bad.write_bytes(good[: second + 40])
  with pytest.raises(DataError, match=r"bad.tfrecord: record 1: truncated"):
    gqn.count_records(bad)
  with pytest.raises(DataError, match="cannot open"):
    list(gqn.read_tfrecord(tmp_path / "absent.tfrecord"))


def test_gqn_bad_records(tmp_path):
  rng = np.random.default_rng(5)
  path = tmp_path / "001-of-001.tfrecord"
  frames, cameras = fx.gqn_scene(rng, views=3)
  # Undecodable JPEG in record 1, view 2.
  blobs = [fx.encode(f, ".jpg") for f in frames[:2]] + [b"\xff\xd8\xff garbage"]
  fx.write_gqn_tfrecord(path, [(frames, cameras)] * 2, jpeg_frames=[None, blobs])
  with pytest.raises(DataError, match=r"001-of-001.tfrecord \(record 1, view 2\): cannot decode"):
    list(gqn.read_tfrecord(path))
  # Wrong frame size.
  small = fx.gqn_scene(rng, views=3, size=32)
  fx.write_gqn_tfrecord(path, [small])
  with pytest.raises(DataError, match=r"\(record 0, view 0\): image is 32x32 .* expected 64x64"):
    list(gqn.read_tfrecord(path, frame_size=64))
  # Non-finite cameras; wrong number of camera values; not an Example.
  cams = cameras.copy()
  cams[1, 3] = np.nan
  fx.write_gqn_tfrecord(path, [(frames, cams)])
  with pytest.raises(DataError, match="record 0: non-finite camera values"):
    list(gqn.read_tfrecord(path))
  fx.write_gqn_tfrecord(path, [(frames, cameras[:2])])
  with pytest.raises(DataError, match="record 0: 3 frames but 10 camera values"):
    list(gqn.read_tfrecord(path))
  with open(path, "wb") as f:
    payload = b"\x0a\x05\xff\xff\xff\xff\xff"
    f.write(
      len(payload).to_bytes(8, "little")
      + fx.TFRecordWriter.masked_crc(len(payload).to_bytes(8, "little"))
    )
    f.write(payload + fx.TFRecordWriter.masked_crc(payload))
  with pytest.raises(DataError, match="record 0: not a tf.train.Example"):
    list(gqn.read_tfrecord(path))


def test_gqn_reader_range_and_view_count(tmp_path):
  rng = np.random.default_rng(6)
  d = tmp_path / gqn.ROOMS / "test"
  d.mkdir(parents=True)
  frames, cameras = fx.gqn_scene(rng)
  cameras[7, 1] = 1.5
  fx.write_gqn_tfrecord(d / "01-of-10.tfrecord", [(frames, cameras)])
  with pytest.raises(DataError, match=r"01-of-10.tfrecord: record 0, view 7: position"):
    list(gqn.GQN(tmp_path).iter_views("test"))
  assert len(list(gqn.GQN(tmp_path, xy_range=(-2, 2)).iter_views("test"))) == 1
  with pytest.raises(DataError, match="record 0: 10 views, need more than num_train_views=10"):
    list(gqn.GQN(tmp_path, num_train_views=10, xy_range=(-2, 2)).iter_views("train"))
  with pytest.raises(DataError, match=r"view 0\): image is 64x64 .* expected 32x32"):
    list(gqn.GQN(tmp_path, image_size=32, xy_range=(-2, 2)).iter_views("train"))


# ---------------------------------------------------------------------------------------------
# SRN cars


def _srn_root(tmp_path, *, instances=("b2", "a1"), views=4, size=32):
  rng = np.random.default_rng(7)
  angles = {}
  for split in ("cars_train", "cars_train_test"):
    for i, inst in enumerate(instances):
      ang = np.stack([rng.uniform(0, 2 * np.pi, views), rng.uniform(0.2, 1.5, views)], -1)
      fx.write_srn_instance(tmp_path / split / inst, rng, ang, size=size, four_lines=(i == 1))
      angles[split, inst] = ang
  return tmp_path, angles


def test_srn_angles_from_camera_centre():
  rng = np.random.default_rng(8)
  az = rng.uniform(0, 2 * np.pi, 50)
  po = rng.uniform(0.01, np.pi - 0.01, 50)
  poses = np.stack([fx.srn_pose(a, p) for a, p in zip(az, po, strict=True)])
  np.testing.assert_allclose(srn.c2w_to_angles(poses), np.stack([az, po], -1), atol=1e-10)
  # Rotation part (OpenCV axes) is not used: the z axis points at the origin.
  np.testing.assert_allclose(poses[:, :3, 2], -poses[:, :3, 3] / 1.3, atol=1e-12)
  on_axis = np.eye(4)
  on_axis[:3, 3] = [0.0, -1e-12, -2.0]
  az0, po0 = srn.c2w_to_angles(on_axis)
  assert 0 <= az0 < 2 * np.pi and po0 == pytest.approx(np.pi)


def test_srn_reader(tmp_path):
  root, angles = _srn_root(tmp_path)
  reader = srn.SRNCars(root, image_size=16)
  assert reader.name == "srn_cars" and reader.pose_names == ("azimuth", "polar")
  assert reader.instances["train"] == ["a1", "b2"] and reader.num_scenes("test") == 2
  records = list(reader.iter_views("train"))
  _check_records(records, pose_dim=2, image_size=16, num_scenes=2)
  np.testing.assert_allclose(records[4]["pose"], angles["cars_train", "b2"][0], atol=1e-6)
  img = imageio.read_image(tmp_path / "cars_train" / "a1" / "rgb" / "000001.png")
  assert img.shape == (32, 32, 3)
  np.testing.assert_array_equal(
    records[1]["image"], cv2.resize(img, (16, 16), interpolation=cv2.INTER_AREA)
  )
  test = list(reader.iter_views("test"))
  np.testing.assert_allclose(test[0]["pose"], angles["cars_train_test", "a1"][0], atol=1e-6)


def test_srn_intrinsics(tmp_path):
  p = tmp_path / "intrinsics.txt"
  p.write_text("131.25 64. 64. 0.\n0. 0. 0.\n1.\n128 128\n")
  k = srn.read_intrinsics(p)
  assert k == dict(focal=131.25, cx=64.0, cy=64.0, height=128, width=128, world2cam=False)
  k = srn.read_intrinsics(p, image_size=64)
  assert (k["focal"], k["cx"], k["cy"], k["height"]) == (65.625, 32.0, 32.0, 64)
  p.write_text("100 80 60 0.\n0. 0. 0.\n1.\n120 160\n0\n")
  k = srn.read_intrinsics(p, image_size=60)
  assert (k["focal"], k["cx"], k["cy"], k["width"]) == (50.0, 30.0, 30.0, 60)
  for text in ("131.25 64. 64.\n0. 0. 0.\n1.\n128 128\n", "a b c 0.\n0. 0. 0.\n1.\n128 128\n", ""):
    p.write_text(text)
    with pytest.raises(DataError, match="intrinsics.txt: bad intrinsics format"):
      srn.read_intrinsics(p)


def test_srn_bad_inputs(tmp_path):
  root, _ = _srn_root(tmp_path, instances=("a1",), views=2)
  inst = root / "cars_train" / "a1"
  reader = srn.SRNCars(root, image_size=16)
  pose = inst / "pose" / "000001.txt"
  good = pose.read_text()
  pose.write_text(good.replace(good.split()[3], "inf", 1))
  with pytest.raises(DataError, match=r"000001.txt: non-finite pose"):
    list(reader.iter_views("train"))
  pose.write_text(" ".join(["0"] * 15 + ["1"]))
  with pytest.raises(DataError, match=r"000001.txt: camera at the origin"):
    list(reader.iter_views("train"))
  pose.write_text("1 2 3")
  with pytest.raises(DataError, match=r"000001.txt: expected 16 numbers"):
    list(reader.iter_views("train"))
  pose.write_text(good)
  png = inst / "rgb" / "000001.png"
  png.write_bytes(png.read_bytes()[:40])
  with pytest.raises(DataError, match=r"rgb/000001.png: cannot decode"):
    list(reader.iter_views("train"))
  png.write_bytes(fx.encode(np.zeros((20, 32, 3), np.uint8), ".png"))
  with pytest.raises(DataError, match=r"rgb/000001.png: image is 20x32 .* expected 32x32"):
    list(reader.iter_views("train"))
  os.remove(pose)
  with pytest.raises(DataError, match=r"000001.png: image has no pose file"):
    list(reader.iter_views("train"))
  os.remove(inst / "intrinsics.txt")
  with pytest.raises(DataError, match=r"a1/intrinsics.txt: cannot read"):
    list(reader.iter_views("train"))
  shutil.rmtree(root / "cars_train_test" / "a1")
  fx.write_srn_instance(root / "cars_train_test" / "zz", np.random.default_rng(0), np.ones((1, 2)))
  with pytest.raises(DataError, match=r"cars_train_test: instances differ"):
    srn.SRNCars(root)
  with pytest.raises(DataError, match=r"cars_val: SRN split directory does not exist"):
    srn.SRNCars(root, split_dirs={"train": "cars_val"})
  (root / "empty").mkdir()
  with pytest.raises(DataError, match=r"empty: no SRN instance folders"):
    srn.SRNCars(root, split_dirs={"test_scenes": "empty"})


# ---------------------------------------------------------------------------------------------
# Gibson rooms


def _gibson_root(tmp_path, areas=("Beach/area2", "Angilola/area1")):
  rng = np.random.default_rng(9)
  metas = {a: fx.write_gibson_area(tmp_path / a, rng, size=24) for a in areas}
  (tmp_path / "Beach" / "not_an_area").mkdir(parents=True, exist_ok=True)
  return tmp_path, metas


def test_gibson_reader(tmp_path):
  root, metas = _gibson_root(tmp_path)
  reader = gibson.GibsonRooms(root, image_size=8)
  assert reader.areas == ["Angilola/area1", "Beach/area2"]
  assert reader.name == "gibson" and reader.pose_names == ("x", "y", "yaw")
  train = list(reader.iter_views("train"))
  test = list(reader.iter_views("test"))
  _check_records(train, pose_dim=3, image_size=8, num_scenes=2)
  _check_records(test, pose_dim=3, image_size=8, num_scenes=2)
  assert len(train) == 2 * 12 and len(test) == 2 * 24
  keys = reader.grid_keys("train")
  assert [k.shape for k in keys] == [(12, 3), (12, 3)]
  assert [tuple(k) for k in keys[0].tolist()] == sorted(metas["Angilola/area1"]["train"])
  file, (x, y, yaw) = metas["Angilola/area1"]["train"][tuple(keys[0][5].tolist())]
  np.testing.assert_allclose(train[5]["pose"], [x, y, np.deg2rad(yaw)], rtol=1e-6)
  img = imageio.read_image(root / "Angilola" / "area1" / file)
  np.testing.assert_array_equal(
    train[5]["image"], cv2.resize(img, (8, 8), interpolation=cv2.INTER_AREA)
  )
  test_keys = reader.grid_keys("test")[1]
  assert test_keys.shape == (24, 3) and np.all(test_keys[0] == test_keys[1])


def test_gibson_yaw_and_neighbours():
  poses = gibson.meta_to_poses(np.array([[0.0, 0.0, 360.0], [0.0, 0.0, -90.0], [1, 2, 45.0]]))
  np.testing.assert_allclose(poses[:, 2], [0.0, 1.5 * np.pi, np.pi / 4], rtol=1e-6)
  keys = np.array([[0, 0, 0], [1, 1, 2], [3, 0, 0], [0, 0, 3], [0, 0, 0]])
  nb = gibson.grid_neighbours(keys)
  assert [n.tolist() for n in nb] == [[1, 4], [0, 3, 4], [], [1], [0, 1]]
  assert gibson.grid_neighbours(keys, include_self=True)[2].tolist() == [2]


def test_gibson_bad_inputs(tmp_path):
  root, metas = _gibson_root(tmp_path, areas=("Angilola/area1",))
  area = root / "Angilola" / "area1"
  reader = gibson.GibsonRooms(root, image_size=8)

  def write(meta, name="train_meta.json"):
    (area / name).write_bytes(pickle.dumps(meta))

  train = metas["Angilola/area1"]["train"]
  key = sorted(train)[3]
  file, pos = train[key]
  write({**train, key: (file, (pos[0], np.nan, pos[2]))})
  with pytest.raises(DataError, match=r"train_meta.json: key \(.*\): non-finite pose"):
    list(reader.iter_views("train"))
  write({**train, key: (file, (2.5, pos[1], pos[2]))})
  with pytest.raises(DataError, match=r"train_meta.json: key .* outside \[0.0, 2.0\]"):
    list(reader.iter_views("train"))
  write({**train, key: (file, (pos[0], pos[1]))})
  with pytest.raises(DataError, match=r"train_meta.json: key .* expected \(image_file"):
    list(reader.iter_views("train"))
  write({"a": 1})
  with pytest.raises(DataError, match=r"train_meta.json: grid key 'a' is not a tuple of 3 ints"):
    list(reader.iter_views("train"))
  write({key: train[key]}, "test_meta.json")
  with pytest.raises(DataError, match=r"test_meta.json: key .* non-empty list"):
    list(reader.iter_views("test"))
  (area / "train_meta.json").write_text('{"json": "not a pickle"}')
  with pytest.raises(DataError, match=r"train_meta.json: not a readable pickle"):
    list(reader.iter_views("train"))
  write(train)
  (area / file).write_bytes(b"not a png")
  with pytest.raises(DataError, match=f"{file}: cannot decode"):
    list(reader.iter_views("train"))
  os.remove(area / file)
  with pytest.raises(DataError, match=f"{file}: image listed in train_meta.json does not exist"):
    list(reader.iter_views("train"))
  with pytest.raises(DataError, match="Gibson root directory does not exist"):
    gibson.GibsonRooms(tmp_path / "absent")
  (tmp_path / "empty").mkdir()
  with pytest.raises(DataError, match=r"empty: no <Building>/<area>/train_meta.json"):
    gibson.GibsonRooms(tmp_path / "empty")


# ---------------------------------------------------------------------------------------------
# Common reader shape


def test_all_readers_share_the_interface():
  for cls in (gqn.GQN, srn.SRNCars, gibson.GibsonRooms, seven_scenes.SevenScenes):
    assert cls.pose_names == sources.get(cls.name).pose_names
    for method in ("num_scenes", "iter_views"):
      assert callable(getattr(cls, method))
