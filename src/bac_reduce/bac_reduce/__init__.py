"""The simulation phase (paper sec. III-D): which calibration parameters matter, and which move together.

* :mod:`.analysis`: sensitivity curves, significance, similarity, the reduced definition (pure numpy);
* :mod:`.objectives`: what campaigns run on (the batch simulator, a synthetic J with a known answer);
* :mod:`.campaigns`: M BO campaigns in lock-step groups, on local processes or a Dask cluster;
* :mod:`.pipeline`: the whole phase, its checks and validation (:func:`run_reduction`);
* :mod:`.report`, :mod:`.plots`: what ``bac reduce`` prints and draws.

The command line is :mod:`bac_reduce.cli` (``bac reduce``); docs/reduce.md explains the method.
"""
