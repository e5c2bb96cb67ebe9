"""Video → clip: input readers, synthetic benchmark scenes, alignment, planes, contacts, the pipeline,
and the CPU path for a plain video (person, cameras, landmarks, sparse surfaces)."""
