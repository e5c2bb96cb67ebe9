"""Video → clip: input readers, synthetic benchmark scenes, alignment, planes, contacts, pipeline."""
