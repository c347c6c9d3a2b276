"""Posed-image data: procedural families (the default), readers for the paper's real datasets,
TFDS storage and the input pipeline.

Every source yields *view records* (see `camrep.data.records`)."""
