"""Earthquake-source location: the estimators (locate), the workflow from traces to a located event
(run), and QuakeML output with uncertainties (quakeml)."""
