"""Tools for working on camrep rather than on its results: the GPU machine's wheelhouse, the
quickstart notebook's outputs, config sweeps, the rooms regression probe, and the compaction of
a comparison archive to one record per run. Run as `python tools/NAME.py ...` from a checkout.
"""
