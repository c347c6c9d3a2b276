"""Posed-image data: procedural families (the default), readers for the paper's real datasets,
TFDS storage and the input pipeline.

Every source yields *view records* (see `camrep.data.records`). The package, lowest first:

  errors, records, sources   the data error, the record format, the one registry of sources
  readers/                   readers of real datasets on disk (GQN, SRN cars, Gibson, 7-Scenes,
                             posed captures) and their file helpers
  procedural/                the procedural families and their renderer
  feed/                      TFDS storage, the data fingerprint, the batch pipeline
  prepare, show, oracle      the commands (`python -m camrep.data.prepare`, `.show`, `.oracle`)
"""
