"""The Bayesian-optimization agent of bac (paper algorithm 1): the ask/tell engine, the campaign state machine
and its journal, the bo_agent node.
"""
