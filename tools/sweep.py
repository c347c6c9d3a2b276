"""Learning curves of config variants: held-out-view PSNR gain over the baseline at each evaluation.

Runs `python -m camrep.main` once per variant (a name and its `--config.*` overrides), several at
once, each in its own workdir under --out, then tabulates `eval/psnr - eval/psnr_baseline` from
every run's metrics.jsonl. On a GPU, several small (`:quick`) runs share the device well; on the
2-core CPU run them one at a time (--parallel=1).

  .venv/bin/python tools/sweep.py --config=configs/gqn.py:quick --out=/tmp/sweep \\
      --steps=3000 --every=500 --parallel=8 \\
      --variant 'base=' \\
      --variant 'lr_rep_3e-3=--config.optax.lr_rep=3e-3' \\
      --variant 'quarter=--config.model.width=0.25'

Writes --out/sweep.md (the table) and --out/sweep.json (every evaluation of every run); the runs'
logs are --out/<name>/log.txt. A variant whose run fails is listed with its exit status and the
last line of its log. Existing workdirs resume (camrep.main's resume-or-init), so a rerun with
more --steps extends the curves.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import shlex
import subprocess
import sys
import time

from camrep.runtime import writers

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def parse_variant(text: str) -> tuple[str, list[str]]:
  """'name=--config.a=1 --config.b=2' -> ("name", ["--config.a=1", "--config.b=2"])."""
  name, sep, overrides = text.partition("=")
  name = name.strip()
  if not sep or not name or not name.replace("_", "").replace("-", "").replace(".", "").isalnum():
    raise argparse.ArgumentTypeError(
      f"variant {text!r}: expected NAME=OVERRIDES with NAME of letters, digits, '_', '-', '.'"
    )
  args = shlex.split(overrides)
  bad = [a for a in args if not a.startswith("--config.")]
  if bad:
    raise argparse.ArgumentTypeError(f"variant {name!r}: not --config.* overrides: {bad}")
  return name, args


def _parse(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
  p.add_argument(
    "--config", required=True, help="config path with variant, e.g. configs/gqn.py:quick"
  )
  p.add_argument("--out", required=True, help="directory for the runs' workdirs and the table")
  p.add_argument("--steps", type=int, default=None, help="total_steps of every run (config's)")
  p.add_argument("--every", type=int, default=None, help="eval_every_steps (config's)")
  p.add_argument("--parallel", type=int, default=1, help="runs at once")
  p.add_argument("--timeout", type=float, default=None, help="seconds per run (none)")
  p.add_argument(
    "--variant",
    action="append",
    type=parse_variant,
    required=True,
    help="NAME=OVERRIDES (repeatable); 'base=' runs the config as it is",
  )
  args = p.parse_args(argv)
  names = [n for n, _ in args.variant]
  if len(set(names)) != len(names):
    p.error(f"variant names must differ: {names}")
  if args.parallel < 1:
    p.error("--parallel must be >= 1")
  return args


def command(args: argparse.Namespace, name: str, overrides: list[str]) -> list[str]:
  """The camrep.main command line of one variant."""
  cmd = [sys.executable, "-m", "camrep.main", f"--config={args.config}"]
  cmd.append(f"--workdir={os.path.join(args.out, name)}")
  if args.steps is not None:
    # One checkpoint at the end only: the sweep wants curves, not resumable midpoints.
    cmd += [f"--config.total_steps={args.steps}", f"--config.ckpt_every_steps={args.steps}"]
  if args.every is not None:
    cmd.append(f"--config.eval_every_steps={args.every}")
  return cmd + overrides


def run_one(args: argparse.Namespace, name: str, overrides: list[str]) -> dict:
  """Runs one variant; returns {name, overrides, returncode, seconds, last_line}."""
  workdir = os.path.join(args.out, name)
  os.makedirs(workdir, exist_ok=True)
  t0 = time.perf_counter()
  with open(os.path.join(workdir, "log.txt"), "w", encoding="utf-8") as log:
    try:
      rc = subprocess.run(
        command(args, name, overrides),
        cwd=ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
        timeout=args.timeout,
        check=False,
      ).returncode
    except subprocess.TimeoutExpired:
      rc = "timeout"
  with open(os.path.join(workdir, "log.txt"), encoding="utf-8", errors="replace") as log:
    lines = [ln.strip() for ln in log.read().replace("\r", "\n").splitlines() if ln.strip()]
  return {
    "name": name,
    "overrides": overrides,
    "returncode": rc,
    "seconds": round(time.perf_counter() - t0, 1),
    "last_line": lines[-1] if lines else "",
  }


def read_curve(workdir: str) -> list[dict]:
  """[{step, psnr, baseline, gain, ssim}] from a run's metrics.jsonl (evaluation rows only)."""
  return [
    {
      "step": int(d["step"]),
      "psnr": d["eval/psnr"],
      "baseline": d["eval/psnr_baseline"],
      "gain": d["eval/psnr"] - d["eval/psnr_baseline"],
      "ssim": d.get("eval/ssim"),
    }
    for d in writers.read_metrics(workdir)
    if "eval/psnr" in d and "eval/psnr_baseline" in d
  ]


def table(results: list[dict]) -> str:
  """Markdown: one row per variant, one column per evaluation step, cells = gain in dB."""
  steps = sorted({r["step"] for res in results for r in res["curve"]})
  head = "| variant | overrides | " + " | ".join(str(s) for s in steps) + " | status |"
  lines = [head, "|" + "---|" * (len(steps) + 3)]
  for res in results:
    by_step = {r["step"]: r["gain"] for r in res["curve"]}
    cells = [f"{by_step[s]:+.2f}" if s in by_step else "" for s in steps]
    status = "ok" if res["returncode"] == 0 else f"exit {res['returncode']}: {res['last_line']}"
    over = " ".join(res["overrides"]) or "(as configured)"
    lines.append(f"| {res['name']} | `{over}` | " + " | ".join(cells) + f" | {status} |")
  return "\n".join(lines) + "\n"


def main(argv=None) -> int:
  args = _parse(argv)
  os.makedirs(args.out, exist_ok=True)
  print(f"{len(args.variant)} runs of {args.config}, {args.parallel} at once, into {args.out}")
  with concurrent.futures.ThreadPoolExecutor(args.parallel) as pool:
    futures = {pool.submit(run_one, args, n, o): n for n, o in args.variant}
    done = {}
    for fut in concurrent.futures.as_completed(futures):
      res = fut.result()
      done[res["name"]] = res
      print(f"  {res['name']}: exit {res['returncode']} after {res['seconds']} s", flush=True)
  results = []
  for name, _ in args.variant:
    res = done[name]
    res["curve"] = read_curve(os.path.join(args.out, name))
    results.append(res)
  md = table(results)
  header = f"PSNR gain over the baseline (dB) at each evaluation: `{shlex.join(sys.argv)}`\n\n"
  with open(os.path.join(args.out, "sweep.md"), "w", encoding="utf-8") as f:
    f.write(header + md)
  with open(os.path.join(args.out, "sweep.json"), "w", encoding="utf-8") as f:
    json.dump({"config": args.config, "runs": results}, f, indent=1)
  print(md, end="")
  return 0 if all(r["returncode"] == 0 for r in results) else 1


if __name__ == "__main__":
  sys.exit(main())
