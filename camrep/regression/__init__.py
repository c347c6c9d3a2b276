"""Camera-pose regression (paper section 4.4, Tables 1 and 2): the targets every representation
gives (`targets`), the regressor's train step and errors (`learner`), one run from config to
results.json (`driver`, `python -m camrep.regression`), and the tables (`tables`)."""
