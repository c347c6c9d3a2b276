"""Tests of camrep.synthesis.evaluate (noise robustness, Gram maps, CLI) on a GQN :smoke run."""

from __future__ import annotations

import json
import os
import shutil

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from camrep import pose as P
from camrep import pose_encodings, settings
from camrep.configs import gibson, gqn, seven_scenes, shapenet_car
from camrep.runtime import checkpoint as ckpt_lib
from camrep.runtime import writers
from camrep.synthesis import components, heldout, restore, synthesizers, train
from camrep.synthesis import evaluate as ev
from camrep.synthesis import gram as gram_lib
from camrep.synthesis import noise as noise_lib
from experiments import noise_figure

pytestmark = [pytest.mark.usefixtures("fast_compile"), pytest.mark.slow]


@pytest.fixture(scope="session")
def workdir(gqn_smoke_run):
  """The session's shared 4-step GQN :smoke run (checkpoints 2 and 4, eval at 4); read-only."""
  return gqn_smoke_run


# Session scope: a module-scoped fixture is rebuilt whenever xdist runs another module's test
# in between (load_run renders the evaluation data: ~20 s each time).
@pytest.fixture(scope="session")
def run(workdir):
  return restore.load_run(workdir)


def _train_eval(workdir):
  return [r for r in writers.read_metrics(workdir) if "eval/psnr" in r][-1]


def test_load_run_restores_checkpoint_params(workdir, run):
  assert run.step == 4 and components.setting(run.config) is settings.GQN
  assert run.config.data.n_context == 3 and run.spec == components.pose_spec(
    gqn.get_config("smoke")
  )
  raw = ocp.PyTreeCheckpointer().restore(os.path.join(workdir, "checkpoints", "4", "state"))
  want = dict(jax.tree_util.tree_flatten_with_path(raw["params"])[0])
  got = dict(jax.tree_util.tree_flatten_with_path(run.params)[0])
  assert want.keys() == got.keys()
  for k, v in want.items():
    np.testing.assert_array_equal(np.asarray(got[k]), v, err_msg=jax.tree_util.keystr(k))


def test_load_run_errors(workdir, tmp_path):
  with pytest.raises(FileNotFoundError, match="does not exist"):
    restore.load_run(str(tmp_path / "nope"))
  with pytest.raises(FileNotFoundError, match="config.json"):
    restore.load_run(str(tmp_path))
  shutil.copy(os.path.join(workdir, "config.json"), tmp_path / "config.json")
  with pytest.raises(FileNotFoundError, match="no checkpoint"):
    restore.load_run(str(tmp_path))
  os.makedirs(tmp_path / "checkpoints")
  with pytest.raises(FileNotFoundError, match="no checkpoint"):
    restore.load_run(str(tmp_path))
  with pytest.raises(ckpt_lib.CheckpointError, match="available"):
    restore.load_run(workdir, step=7)
  assert ev.main(["--workdir", str(tmp_path / "nope")]) == 2


def test_default_quantisation():
  configs = {"gqn": gqn, "car": shapenet_car, "gibson": gibson, "seven_scenes": seven_scenes}
  got = {k: noise_lib.default_quantisation(m.get_config("smoke")) for k, m in configs.items()}
  assert got == {"gqn": "random", "car": "random", "gibson": "nearest", "seven_scenes": "nearest"}


def test_noise_levels(workdir, run):
  batches = heldout.eval_batches(run.model, run.train_pipe, run.test_pipe)
  key = jax.random.key(3)
  res = noise_lib.noise_robustness(
    run, key=key, alphas=[0.0, 0.2, 0.2], quantisation="nearest", batches=batches
  )
  assert res["step"] == 4 and res["quantisation"] == "nearest"
  n = sum(len(b["scene"]) for b in batches)
  assert res["num_images"] == n and res["psnr_per_image"].shape == (3, n)
  # alpha = 0 with rounding is the training loop's evaluation.
  evals = _train_eval(workdir)
  np.testing.assert_allclose(res["psnr"][0], evals["eval/psnr"], rtol=1e-5)
  np.testing.assert_allclose(res["ssim"][0], evals["eval/ssim"], rtol=1e-4)
  assert np.all(np.isfinite(res["psnr"])) and np.all(np.isfinite(res["ssim"]))
  # Fresh noise per level: two levels with the same alpha differ.
  assert not np.allclose(res["psnr_per_image"][1], res["psnr_per_image"][2])
  # alpha > 0 changes the predictions.
  assert not np.allclose(res["psnr_per_image"][0], res["psnr_per_image"][1])


def test_beta_and_noise_statistics(run):
  rep, spec = run.params["rep"], run.spec
  betas = noise_lib.grid_betas(rep, spec)
  assert set(betas) == {"xy", "yaw"}
  for name, beta in betas.items():
    assert beta.shape == (spec.dim,)
    grid = np.asarray(P.grid_vectors(rep, spec, name))
    np.testing.assert_allclose(beta, grid.std(axis=0), rtol=1e-5, atol=1e-7)
    assert np.all(beta > 0)
  # The added noise has per-element std alpha * beta_i, is independent per image, and is only
  # a function of the image's key.
  n = 4000
  poses = jnp.tile(jnp.asarray([[[0.13, -0.42, 1.0]]], jnp.float32), (n, 1, 1))
  _, _, k_noise = noise_lib.image_keys(jax.random.key(0), jnp.arange(n))
  exact = jax.jit(lambda r, p: noise_lib.pose_vectors(r, spec, p, None, mode="nearest"))(rep, poses)
  noisy = noise_lib.add_noise(exact, spec, k_noise, alpha=0.3, betas=betas)
  for name in spec.names:
    diff = np.asarray(noisy[name] - exact[name])[:, 0]  # (n, d)
    np.testing.assert_allclose(diff.std(axis=0), 0.3 * betas[name], rtol=0.08)
    assert abs(np.corrcoef(diff[:, 0], diff[:, 1])[0, 1]) < 0.08
  zero = noise_lib.add_noise(exact, spec, k_noise, alpha=0.0, betas=betas)
  for name in spec.names:
    np.testing.assert_array_equal(zero[name], exact[name])


def test_gram_maps(run):
  grams = gram_lib.gram_maps(run)
  xy = run.spec.dof("xy")
  assert grams["xy"].shape == (xy.n_grid, xy.n_grid) == (441, 441)
  assert grams["yaw"].shape == (360, 360)  # 1-degree vectors over the periodic range
  for g in grams.values():
    np.testing.assert_allclose(g, g.T, atol=1e-6)
  # Yaw vectors have unit norm: exactly at the grid points (every 10 degrees), and up to the
  # norm error of the Taylor exp (exp_method "taylor2") in between.
  diag = np.diag(grams["yaw"])
  np.testing.assert_allclose(diag[::10], 1.0, atol=1e-5)
  np.testing.assert_allclose(diag, 1.0, atol=1e-2)
  # Polar with block_norm: every block has norm 1 / n_blocks, so |v|^2 = 1 / n_blocks.
  assert xy.block_norm and run.spec.n_blocks == 2
  np.testing.assert_allclose(np.diag(grams["xy"]), 1.0 / run.spec.n_blocks, atol=1e-5)


def test_cli_writes_all_files(workdir, tmp_path, capsys):
  out = str(tmp_path / "eval")
  assert ev.main(["--workdir", workdir, "--levels", "2", "--out", out]) == 0
  text = capsys.readouterr().out
  assert "alpha" in text and "PSNR" in text and "wrote" in text and out in text
  names = {"noise.json", "noise.png", "gram_xy.png", "gram_yaw.png", "gram.npz"}
  names |= {"noise.pdf", "gram_xy.pdf", "gram_yaw.pdf"}  # vector twins for a paper
  assert names <= set(os.listdir(out))
  record = json.load(open(os.path.join(out, "noise.json")))
  assert record["alphas"] == [0.0, 0.025] and record["step"] == 4
  assert record["quantisation"] == "random" and len(record["psnr"]) == 2
  assert record["beta"]["xy"]["d"] == 8 and record["beta"]["yaw"]["mean"] > 0
  for f in ("noise.png", "gram_xy.png", "gram_yaw.png"):
    im = cv2.imread(os.path.join(out, f))
    assert im is not None and im.shape[0] >= 300 and im.shape[1] >= 300, f
  with np.load(os.path.join(out, "gram.npz")) as z:
    assert z["yaw"].shape == (360, 360) and z["xy_values"].shape == (441, 2)
  capsys.readouterr()
  assert ev.main(["--workdir", workdir, "--what", "loss"]) == 2  # one error: line, no traceback
  assert "error: --what takes a comma-separated subset of noise,gram" in capsys.readouterr().err
  # Explicit noise levels (how much a model uses its pose: large alphas wipe the pose out).
  out2 = str(tmp_path / "alphas")
  assert ev.main(["--workdir", workdir, "--what", "noise", "--alphas", "0,3", "--out", out2]) == 0
  assert json.load(open(os.path.join(out2, "noise.json")))["alphas"] == [0.0, 3.0]
  for bad in ("0,x", "-1", ","):
    assert ev.main(["--workdir", workdir, "--alphas", bad]) == 2
    assert "error: --alphas takes" in capsys.readouterr().err
  # A decoder has no latents: GQN's generator's flag is refused, not silently ignored.
  out3 = str(tmp_path / "temperature")
  assert ev.main(["--workdir", workdir, "--draw_temperature", "0", "--out", out3]) == 2
  assert "error: --draw_temperature: the run in" in capsys.readouterr().err
  assert not os.path.exists(out3)


@pytest.mark.parametrize("kind", ["lowdim", "mlp"])
def test_other_pose_inputs_train_and_take_noise(kind, tmp_path):
  """The noise figure's comparison inputs: GQN's low-dimensional pose vector and the
  supplement's MLP embedding train in the same loop and go through the same noise evaluation."""
  config = gqn.get_config("smoke")
  config.rep.kind = kind
  config.total_steps = 2
  last = train.train_and_evaluate(config, str(tmp_path))
  assert last["train/finite"] == 1.0 and "train/rot_xy" not in last
  run = restore.load_run(str(tmp_path))
  spec = run.spec
  poses = jnp.asarray([[0.1, -0.2, 1.0], [0.5, 0.3, 4.0]], jnp.float32)
  pose_input = synthesizers.pose_input(components.resolve(run.config), spec)
  vecs = pose_input.embed(run.params["rep"], poses)
  betas = noise_lib.grid_betas(run.params["rep"], spec, run.model)
  if kind == "lowdim":
    assert run.params["rep"] == {}
    z, pitch = pose_encodings.gqn_lowdim_constants(run.config.data.family)
    assert (pose_input.camera_height, pose_input.pitch) == (z, pitch)
    np.testing.assert_allclose(vecs["xy"], [[0.1, -0.2, z], [0.5, 0.3, z]], atol=1e-7)
    np.testing.assert_allclose(
      vecs["yaw"][0], [np.sin(1.0), np.cos(1.0), np.sin(pitch), np.cos(pitch)], atol=1e-6
    )
    # The constants (camera height, pitch) do not vary over the grid: no noise on them.
    assert betas["xy"][2] < 1e-6 and np.all(betas["yaw"][2:] < 1e-6)
    assert np.all(betas["xy"][:2] > 0) and np.all(betas["yaw"][:2] > 0)
  else:
    assert {d.name for d in spec.dofs} == set(run.params["rep"])
    for name in spec.names:
      assert vecs[name].shape == (2, spec.dim) and np.all(betas[name] > 0)
      np.testing.assert_allclose(np.linalg.norm(vecs[name], axis=-1), 1.0, rtol=1e-5)
  result = noise_lib.noise_robustness(run, key=jax.random.key(0), alphas=[0.0, 0.3])
  assert result["psnr"][0] == pytest.approx(_train_eval(str(tmp_path))["eval/psnr"], abs=1e-4)
  assert result["psnr"][1] != result["psnr"][0]
  grams = gram_lib.gram_maps(run)
  assert set(grams) == set(spec.names)


def test_noise_figure_script(tmp_path):
  """experiments/noise_figure.py reads workdirs only and writes the figure and table."""
  nf = noise_figure
  alphas = [0.0, 0.15, 0.3]
  runs = []
  for kind, psnr in (("grid", [20.0, 19.5, 19.0]), ("lowdim", [20.5, 17.0, 14.0])):
    wd = tmp_path / kind
    (wd / "eval").mkdir(parents=True)
    (wd / "config.json").write_text(json.dumps({"rep": {"kind": kind}}))
    noise = {"setting": "gqn", "step": 10, "alphas": alphas, "psnr": psnr, "num_images": 4}
    noise["ssim"] = [0.5, 0.4, 0.3]
    (wd / "eval" / "noise.json").write_text(json.dumps(noise))
    runs.append(str(wd))
  png, md = tmp_path / "out" / "noise.png", tmp_path / "out" / "noise.md"
  assert nf.main(["--runs", *runs, "--png", str(png), "--md", str(md)]) == 0
  img = cv2.imread(str(png))
  assert img is not None and img.shape[1] > 2 * img.shape[0] > 600  # two panels side by side
  assert (tmp_path / "out" / "noise.pdf").read_bytes().startswith(b"%PDF")
  text = md.read_text()
  assert "| 0.300 | 19.00 / 0.300 | 14.00 / 0.300 |" in text
  assert "ours (learned) 1.00 dB, GQN low-dim pose 6.50 dB" in text
  # The table gives the runs back (how results/quick/noise_*.png are redrawn without the workdirs).
  back = nf.from_markdown(text, "gqn")
  assert [r["label"] for r in back] == ["ours (learned)", "GQN low-dim pose"]
  assert back[1]["psnr"] == [20.5, 17.0, 14.0] and back[0]["alphas"] == alphas
  redrawn = tmp_path / "redrawn.png"
  assert nf.main(["--from_md", str(md), "--png", str(redrawn), "--setting", "gqn"]) == 0
  assert cv2.imread(str(redrawn)).shape == img.shape
  # Runs of the same kind (seeds) become one curve: their mean, with a band.
  seeds = nf.by_label([*nf.from_markdown(text), {**back[0], "psnr": [22.0, 21.5, 21.0]}], "psnr")
  np.testing.assert_allclose(seeds["ours (learned)"], [[20.0, 19.5, 19.0], [22.0, 21.5, 21.0]])
  # A run without its noise curve is a clear error.
  (tmp_path / "grid" / "eval" / "noise.json").unlink()
  assert nf.main(["--runs", *runs, "--png", str(png), "--md", str(md)]) == 2


def test_noise_figure_groups_seeds_by_pose_input_with_a_band(tmp_path):
  """Runs are grouped by their config's pose input (not their order or
  directory), each group drawn as its mean with a min-max band and tabled as "mean [min, max]";
  the table redraws the same band."""
  nf = noise_figure
  alphas = [0.0, 0.3]
  runs = []
  for name, config, psnr in (
    ("a", {"rep": {"kind": "grid"}}, [20.0, 19.0]),
    ("b", {"rep": {"kind": "lowdim"}}, [21.0, 15.0]),
    ("c", {"rep": {"kind": "grid"}}, [22.0, 20.0]),
    ("d", {"rep": {"kind": "grid"}}, [21.0, 18.0]),
    ("e", {"rep": {"kind": "lowdim"}, "model": {"kind": "convdraw"}}, [19.0, 18.5]),
    ("f", {"rep": {"kind": "lowdim"}}, [20.0, 13.0]),
  ):
    wd = tmp_path / name
    (wd / "eval").mkdir(parents=True)
    (wd / "config.json").write_text(json.dumps(config))
    noise = {"setting": "gqn", "step": 10, "alphas": alphas, "psnr": psnr, "num_images": 4}
    noise["ssim"] = [0.5, psnr[1] / 100]
    (wd / "eval" / "noise.json").write_text(json.dumps(noise))
    runs.append(str(wd))
  png, md = tmp_path / "out" / "noise.png", tmp_path / "out" / "noise.md"
  assert nf.main(["--runs", *runs, "--png", str(png), "--md", str(md)]) == 0
  text = md.read_text()
  head = (
    "| alpha | ours (learned) PSNR / SSIM (3 seeds) | GQN low-dim pose PSNR / SSIM (2 seeds) "
    "| GQN (ConvDRAW) PSNR / SSIM |"
  )
  assert head in text
  row = (
    "| 0.300 | 19.00 [18.00, 20.00] / 0.190 [0.180, 0.200] | 14.00 [13.00, 15.00] / "
    "0.140 [0.130, 0.150] | 18.50 / 0.185 |"
  )
  assert row in text
  assert "ours (learned) 2.00 [1.00, 3.00] dB, GQN low-dim pose 6.50 [6.00, 7.00] dB" in text
  assert "GQN (ConvDRAW) 0.50 dB" in text
  # The figure: one line per pose input, a filled band for each group of seeds.
  fig = nf.figure([nf.load(w) for w in runs])
  ax = fig.axes[0]
  assert [line.get_label() for line in ax.lines] == [
    "ours (learned) (mean of 3 seeds)",
    "GQN low-dim pose (mean of 2 seeds)",
    "GQN (ConvDRAW)",
  ]
  np.testing.assert_allclose(ax.lines[0].get_ydata(), [21.0, 19.0])
  assert len(ax.collections) == 2
  band = ax.collections[0].get_paths()[0].vertices[:, 1]
  assert band.min() == pytest.approx(18.0) and band.max() == pytest.approx(22.0)
  assert ax.get_title() == "PSNR vs pose noise (gqn)"
  named = nf.figure([nf.load(w) for w in runs], "chair, car setting")
  assert [a.get_title() for a in named.axes] == [
    "PSNR vs pose noise (chair, car setting)",
    "SSIM vs pose noise (chair, car setting)",
  ]
  # Redrawn from the table: the same means and bands.
  back = nf.from_markdown(text, "gqn")
  assert back[0]["seeds"] == 3 and back[0]["psnr"] == [21.0, 19.0]
  assert back[0]["psnr_band"] == ([20.0, 18.0], [22.0, 20.0]) and "seeds" not in back[2]
  again = nf.figure(back).axes[0]
  assert [line.get_label() for line in again.lines] == [line.get_label() for line in ax.lines]
  np.testing.assert_allclose(
    again.collections[0].get_paths()[0].vertices, ax.collections[0].get_paths()[0].vertices
  )


def test_the_frozen_generator_control_is_its_own_curve_from_workdir_and_record(tmp_path):
  """A view-synthesis run with `rep.freeze_generators` is labelled as the control, not as ours,
  read from its workdir or from its compact record (which keeps the flag); a learned run's
  record leaves the unset flag out, as records did before it was kept."""
  from camrep.regression import runs as runs_lib

  alphas = [0.0, 0.3]
  dirs = []
  for name, frozen, psnr in (("learned", False, [20.0, 19.0]), ("frozen", True, [19.0, 17.0])):
    wd = tmp_path / name
    (wd / "eval").mkdir(parents=True)
    config = {"seed": 0, "rep": {"kind": "grid", "freeze_generators": frozen}}
    (wd / "config.json").write_text(json.dumps(config))
    (wd / "final_metrics.json").write_text(json.dumps({"complete": True, "step": 10}))
    (wd / "metrics.jsonl").write_text(json.dumps({"step": 10, "eval/psnr": psnr[0]}) + "\n")
    noise = {"setting": "gibson", "step": 10, "alphas": alphas, "psnr": psnr, "num_images": 4}
    noise["ssim"] = [0.5, 0.4]
    (wd / "eval" / "noise.json").write_text(json.dumps(noise))
    dirs.append(str(wd))
  records = []
  for wd in dirs:
    rec = os.path.join(wd + "_record", runs_lib.RECORD_FILE)
    runs_lib.write_record(runs_lib.compact(runs_lib.load(wd)), rec)
    records.append(os.path.dirname(rec))
  assert runs_lib.load(records[0]).config == {"seed": 0, "rep": {"kind": "grid"}}
  assert runs_lib.load(records[1]).config["rep"] == {"kind": "grid", "freeze_generators": True}
  for group in (dirs, records):
    loaded = [noise_figure.load(w) for w in group]
    assert [r["label"] for r in loaded] == ["ours (learned)", "ours, generators frozen"]
    png, md = tmp_path / "noise.png", tmp_path / "noise.md"
    assert noise_figure.main(["--runs", *group, "--png", str(png), "--md", str(md)]) == 0
    assert "ours (learned) 1.00 dB, ours, generators frozen 2.00 dB" in md.read_text()
