"""The paper's tables and figures, each a script that only reads finished runs (workdirs or their
compact records, `camrep.regression.runs`) and writes Markdown, PNG and PDF:

  table1.py          Table 1 (car, rooms, area columns) with the learning-rate selection
  table2.py          Table 2 (per 7-Scenes trajectory)
  lead_table.py      every column in one table: ours against the best hand-designed target
                     (chosen on validation), seed-level intervals, Holm-adjusted verdicts
  claims_table.py    each of the paper's claims against the records, with its verdict
  coverage.py        the lead table's intervals' coverage, simulated in the records' regimes
  learning_curve.py  validation and held-out PSNR curves, bands over seeds
  noise_figure.py    PSNR as the query pose is noised (the paper's section 4.3)
  seed_spread.py     where ours' spread over seeds comes from (crossed seeds)
  view_failures.py   test views every run gets badly wrong, per capture
  lvsm_table.py      the multi-view transformer's camera conditionings, with verdicts

Run as `python experiments/NAME.py ...` from a checkout (`python -m experiments.NAME` for
claims_table, which imports noise_figure); the comparison launcher
(`python -m camrep.comparison`) runs them over its runs.
"""
