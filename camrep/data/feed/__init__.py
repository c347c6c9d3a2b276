"""From a source's view records to the train step's batches: storage, identity and the pipeline.

storage      TFDS ArrayRecord storage of any view source (build, sidecar index, read back)
fingerprint  what identifies a run's data (procedural or prepared), checked at resume
pipeline     the input pipeline (grain): batches of posed views for a pmapped step
batches      the batch type (`ViewBatch`) and its shape template built without data
draws        numpy's `Generator.choice` / `integers` reproduced for many scenes at once (the
             pipeline's view choice)
"""
