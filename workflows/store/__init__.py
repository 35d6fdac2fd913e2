"""The run's store as the workflow lays it out: :mod:`~workflows.store.layout` (paths, array
names, point roles), :mod:`~workflows.store.assembly` (chunks assembled from ingest's parts),
:mod:`~workflows.store.terrain` (each scene's terrain model) and
:mod:`~workflows.store.retention` (a store removed after its run). The generic codec (packs,
appended record arrays, checksums, done-marks) is :mod:`pipeline.store`."""
