"""The paper's claims against camrep's records, one row per claim and setting.

  python experiments/claims_table.py --records results/converge --out results/converge/claims.md

Reads RECORDS/regression (as experiments/lead_table.py does) and RECORDS/synthesis (the
view-synthesis records: run.json, or workdirs with eval/noise.json, named <column>[_<input>]_seed<k>
as `python -m camrep.comparison` names them). Rows:

  - pose regression, per lead-table row: "ours is a better regression target than the best
    hand-designed representation"; the paper's ours vs its best hand-designed (Tables 1 and 2;
    – where the paper has no such column); camrep's ratio ours / best with its seed-level 95% t
    interval, how many hand-designed representations ran in the column (the best was chosen
    on validation among them), and the seed count; the verdict (Holm-adjusted over the lead
    table, as there);
  - robustness to pose noise (the paper's Figure 5 and the supplement's MLP figure), per setting
    and compared pose input: "ours loses less PSNR than <input> as the query pose is noised";
    camrep's PSNR lost by the largest noise magnitude (mean over seeds, ours vs the other) and
    the difference with its 95% Welch t interval over seeds (`stats.welch_interval`);
  - view-synthesis quality (Figure 5 at noise 0): "ours is comparable to GQN on the rooms, better
    on the car, and GQN fails on the area"; camrep's held-out PSNR of ours and of GQN's own
    generator (ConvDRAW) where it ran, the difference with its Welch interval;
  - the view-synthesis control (not a claim of the paper), per setting where it ran: ours against
    the same grid with its generators frozen at their initialisation (`rep.freeze_generators`),
    in held-out PSNR at noise 0 and in PSNR lost by the largest noise magnitude, each difference
    with its Welch interval: whether learning the generators is what helps.

A claim whose comparison was not run says so ("not run"), naming what is missing. Each row names
what the data is: a procedural family, a render (NeRF-synthetic) or a real capture. The paper
gives its noise and synthesis results as figures only, so its column there describes the figure.
"""

from __future__ import annotations

import argparse
import collections
import glob
import os
import re
import sys
from collections.abc import Sequence

import numpy as np

from camrep.regression import lead, stats
from camrep.regression import tables as C
from experiments import noise_figure

# Pose inputs ours is compared with under noise, and what the paper says of each (Figure 5:
# GQN's low-dimensional pose; the supplement: the MLP embedding, car only).
NOISE_CLAIMS = {
  "lowdim": "Fig. 5: GQN's low-dim pose degrades quickly, ours barely (figure only)",
  "mlp": "supplement, car: the MLP embedding degrades more than ours (figure only)",
  "convdraw": "Fig. 5: GQN degrades quickly, ours barely (figure only)",
}
# The paper's Figure 5 at noise 0, per setting: ours against GQN.
QUALITY_CLAIMS = {
  "gqn": "ours a bit worse than but comparable to GQN (figure only)",
  "car": "ours more consistent and clearer than GQN (figure only)",
  "gibson": "GQN fails to generalise, ours does not (figure only)",
}
SETTING_NAMES = {"car": "car", "gqn": "rooms", "gibson": "area", "seven_scenes": "7-Scenes"}
HEADER = ("claim", "setting", "paper", "camrep [95%]", "seeds", "verdict", "data")


def _name(column: str) -> str:
  if column.startswith("car_"):
    return f"{column[4:]} (car setting)"
  return SETTING_NAMES.get(column, column)


def regression_rows(regression: str) -> list[list[str]]:
  """One row per lead-table row (ours only; controls are the lead table's)."""
  found, adjusted = lead.compared(regression)
  out = []
  for r, adj in zip(found, adjusted, strict=True):
    if r.representation != "ours":
      continue
    c = r.comparison
    camrep = "–"
    if c is not None:
      camrep = f"ours / {c.baseline} {stats.fmt_interval(c.ratio, digits=2)}"
      camrep += f" (best of {r.candidates} hand-designed)"
    verdict = c.verdict(adj) if c is not None else "–"
    words = {"better": "holds", "tie": "not shown (tie)", "worse": "reversed (ours worse)"}
    out.append(
      [
        "pose regression: ours is a better target than the best hand-designed",
        r.column.label,
        r.paper,
        camrep,
        r.seeds,
        f"**{words.get(verdict, verdict)}** (Holm, p = {adj:.3f})" if c else "–",
        r.data,
      ]
    )
  return out


def synthesis_runs(synthesis: str) -> dict[tuple[str, str], list[dict]]:
  """{(column, pose input kind): runs} of the view-synthesis records with noise results."""
  out = collections.defaultdict(list)
  for d in sorted(glob.glob(os.path.join(synthesis, "*"))):
    m = re.fullmatch(r"(.+?)(?:_(mlp|lowdim|convdraw|frozen_gen))?_seed\d+", os.path.basename(d))
    if m is None:
      continue
    try:
      run = noise_figure.load(d)
    except FileNotFoundError:
      continue
    out[m.group(1), run["kind"]].append(run)
  return out


def _drop(run: dict) -> float:
  return float(run["psnr"][0] - run["psnr"][-1])


def _fmt_diff(a: np.ndarray, b: np.ndarray) -> tuple[str, str]:
  m, lo, hi = stats.welch_interval(a, b)
  if not np.isfinite(lo):
    return f"{m:+.2f} dB", "not shown (one seed)"
  return f"{m:+.2f} [{lo:+.2f}, {hi:+.2f}] dB", ("lower" if hi < 0 else "higher" if lo > 0 else "")


def _noise_paper(column: str, kind: str) -> str:
  if column.startswith("car_"):
    return "– (the paper has no captures)"
  if kind == "mlp" and column != "car":
    return "– (the paper's MLP figure is the car's)"
  if column not in QUALITY_CLAIMS:
    return "– (not in the paper's Fig. 5)"
  return NOISE_CLAIMS[kind]


def noise_rows(groups, kinds: dict[str, str]) -> list[list[str]]:
  """Per column with ours' noise results: one row per other pose input that ran, and a "not
  run" row where the paper's Figure 5 compares with GQN's low-dim pose and camrep did not."""
  out = []
  for column in sorted({c for c, k in groups if k == "grid"}):
    ours = groups[column, "grid"]
    alpha = ours[0]["alphas"][-1]
    a = np.array([_drop(r) for r in ours])
    others = [k for k in ("lowdim", "mlp", "convdraw") if (column, k) in groups]
    if column in QUALITY_CLAIMS and "lowdim" not in others:
      out.append(
        [
          "noise robustness: ours loses less PSNR than GQN's low-dim pose",
          _name(column),
          NOISE_CLAIMS["lowdim"],
          f"ours loses {a.mean():.2f} dB by alpha {alpha:g}; GQN's low-dim pose not run",
          str(len(a)),
          "**not run**",
          kinds.get(column, "?"),
        ]
      )
    for k in others:
      b = np.array([_drop(r) for r in groups[column, k]])
      diff, side = _fmt_diff(a, b)
      verdict = {"lower": "holds", "higher": "reversed", "": "not shown (tie)"}.get(side, side)
      out.append(
        [
          f"noise robustness: ours loses less PSNR than {noise_figure.LABELS.get(k, k)}",
          _name(column),
          _noise_paper(column, k),
          f"lost by alpha {alpha:g}: ours {a.mean():.2f}, other {b.mean():.2f}; difference {diff}",
          f"{len(a)}/{len(b)}",
          f"**{verdict}** (unadjusted)",
          kinds.get(column, "?"),
        ]
      )
  return out


def quality_rows(groups, kinds: dict[str, str]) -> list[list[str]]:
  """Per setting of the paper's Figure 5: ours' held-out PSNR at noise 0 against GQN's own
  generator where it ran."""
  out = []
  for column, paper in QUALITY_CLAIMS.items():
    ours = groups.get((column, "grid"), [])
    gqn = groups.get((column, "convdraw"), [])
    a = np.array([r["psnr"][0] for r in ours])
    if not len(a):
      continue
    if not gqn:
      cam, seeds, verdict = (
        f"ours {a.mean():.2f} dB; GQN (ConvDRAW) not run",
        str(len(a)),
        "not run",
      )
    else:
      b = np.array([r["psnr"][0] for r in gqn])
      diff, side = _fmt_diff(a, b)
      cam = f"ours {a.mean():.2f}, GQN {b.mean():.2f} dB; difference {diff}"
      seeds = f"{len(a)}/{len(b)}"
      verdict = {"lower": "ours worse", "higher": "ours better", "": "level (tie)"}.get(side, side)
    out.append(
      [
        "view synthesis: held-out PSNR against GQN",
        _name(column),
        paper,
        cam,
        seeds,
        f"**{verdict}**",
        kinds.get(column, "?"),
      ]
    )
  return out


def control_rows(groups, kinds: dict[str, str]) -> list[list[str]]:
  """Per column where the frozen-generator control ran beside ours: its held-out PSNR at noise 0
  and its PSNR lost by the largest noise magnitude, each against ours'."""
  out = []
  for column in sorted({c for c, k in groups if k == "frozen_gen" and (c, "grid") in groups}):
    ours, frozen = groups[column, "grid"], groups[column, "frozen_gen"]
    alpha = ours[0]["alphas"][-1]
    for what, value, words in (
      ("held-out PSNR at noise 0", lambda r: float(r["psnr"][0]), ("ours higher", "ours lower")),
      (f"PSNR lost by alpha {alpha:g}", _drop, ("ours loses more", "ours loses less")),
    ):
      a, b = np.array([value(r) for r in ours]), np.array([value(r) for r in frozen])
      diff, side = _fmt_diff(a, b)
      verdict = {"higher": words[0], "lower": words[1], "": "not shown (tie)"}
      out.append(
        [
          f"control: learned generators against frozen ones, {what}",
          _name(column),
          "– (a control; not in the paper)",
          f"ours {a.mean():.2f}, frozen {b.mean():.2f} dB; difference {diff}",
          f"{len(a)}/{len(b)}",
          f"**{verdict.get(side, side)}** (unadjusted)",
          kinds.get(column, "?"),
        ]
      )
  return out


def note(rows: list[list[str]], *, controls: bool, extrapolated: bool) -> str:
  """The table's note: how each verdict is taken (`controls`: with control rows); the width of
  intervals where a row rests on fewer than 5 seeds; the captures' extrapolated validation split
  where a capture's records used it (`extrapolated`)."""
  text = (
    "Verdicts: pose regression from the seed-level t interval of ours / best hand-designed "
    "(chosen on validation), Holm-adjusted over the lead table's comparisons; "
    + ("noise, synthesis and the control" if controls else "noise and synthesis")
    + " from the 95% Welch t interval of the difference of per-seed means (ours minus the "
    "other; independent seeds; unadjusted)."
  )
  counts = [int(n) for r in rows for n in re.findall(r"\d+", r[4])]
  if counts and min(counts) < 5:
    n = min(counts)
    text += (
      f" Intervals at {n} seeds are wide (t with {n - 1} degrees of freedom): a tie says the "
      "records cannot tell, not that the two are equal."
    )
  else:
    text += " A tie says the records cannot tell, not that the two are equal."
  if extrapolated:
    text += (
      " Capture rows: the baseline is chosen on each capture's validation split, the last 10% of "
      "its views, which on the LLFF captures are extrapolated views (the representations best "
      "there are poor on test)."
    )
  return text


def build(records: str) -> str:
  """The Markdown claims table of RECORDS (its regression/ and synthesis/).

  Raises:
    FileNotFoundError: RECORDS/regression holds no regression runs.
  """
  regression = os.path.join(records, "regression")
  kinds, extrapolated = {}, False
  for d in sorted(glob.glob(os.path.join(regression, "*"))):
    runs = C.load_results([os.path.join(d, "ours", "*")])
    if runs:
      kinds[os.path.basename(d)] = lead.data_kind(runs[0])
      if os.path.basename(d).startswith("car_"):  # a capture's column
        split = str(runs[0].get("data", {}).get("validation", ""))
        extrapolated |= split.startswith("last ")
  rows = regression_rows(regression)
  groups = synthesis_runs(os.path.join(records, "synthesis"))
  controls = control_rows(groups, kinds)
  rows += noise_rows(groups, kinds) + quality_rows(groups, kinds) + controls
  text = note(rows, controls=bool(controls), extrapolated=extrapolated)
  return C.markdown_table(HEADER, rows) + "\n\n" + text


def main(argv: Sequence[str] | None = None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--records", required=True, help="RECORDS: holds regression/ and synthesis/")
  p.add_argument("--out", default="", help="Markdown file to write (default: print only)")
  args = p.parse_args(argv)
  try:
    text = build(args.records)
  except (FileNotFoundError, C.TableError, ValueError) as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  print(text)
  if args.out:
    with open(args.out, "w", encoding="utf-8") as f:
      f.write(text + "\n")
  return 0


if __name__ == "__main__":
  sys.exit(main())
