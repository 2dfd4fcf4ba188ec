"""Algorithm 1 of bac: run segmentation (cut and align), KPI scoring, the Bayesian-optimization engine
and agent node with its campaign journal, the simulation-phase parameter reduction, rescoring and
reports.
"""
