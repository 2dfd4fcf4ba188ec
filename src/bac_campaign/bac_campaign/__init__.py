"""Campaign tools of bac: the campaign recorder and bag player nodes, offline rescoring, replay, reports,
simulated runs to bags.
"""
