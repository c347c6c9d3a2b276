"""What every training loop uses, whatever it trains: checkpoints, metric writers, progress lines,
image grids and plots, workdir checks. Imports nothing above `camrep.lie`/`camrep.pose`."""
