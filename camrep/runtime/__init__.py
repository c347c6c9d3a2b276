"""What every training loop uses, whatever it trains: the run frame and its fit loop (`frame`),
config fields declared once (`validate`, `runconfig`), checkpoints, metric writers, progress
lines, image grids and plots, workdir checks. Names no model and no stage; imports nothing above
`camrep.lie`/`camrep.pose`."""
