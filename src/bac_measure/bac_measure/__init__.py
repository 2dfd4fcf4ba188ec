"""The measurement chain of bac: cut and align of each run (segmentation), the comfort KPI, bag reading and
writing, the run_segmenter and kpi_scorer nodes.
"""
