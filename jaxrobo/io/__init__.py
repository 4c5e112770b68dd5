"""Run files: run directories that are never lost or mixed (:mod:`~jaxrobo.io.rundir`: staging, publishing,
refusals, the source hash) and what a run writes and reads back (:mod:`~jaxrobo.io.results`)."""
