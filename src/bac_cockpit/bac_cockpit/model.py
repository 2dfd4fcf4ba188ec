"""The GP view of the page: the posterior mean of J over two tuned dimensions, the trials on it, the
recommendation.

The GP is fitted again on the journal's scored runs with the live campaign's settings
(:func:`bac_campaign.report.refit_engine`, as ``bac report`` draws its contour), so the page and the report
show the same model. With more than two tuned dimensions the two most important ones are drawn (the shortest
fitted ARD lengthscales on the unit cube) and the others held at the recommendation; with one, the mean and
its band along it.

:func:`compute_model` is a plain function of the campaign folder, so the node can run it in a worker process
(a fit takes about a second: never on the executor, never holding the node's GIL). The worker keeps its engine
between calls and tells it only the new runs, so each fit starts from the last one's hyperparameters, as the
live agent's engine does (and costs less); the first call, and ``bac cockpit`` on a folder, fit from scratch
exactly as ``bac report`` does.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from bac_cockpit.state import finite_or_none

GRID = 41
# campaign folder -> (engine, the (params, J) it was told, the journal's engine options): the worker's engines
_ENGINES: dict[str, tuple[Any, list[tuple[dict[str, float], float, dict[str, float]]], Any]] = {}


def _engine(camp: Any, key: str) -> Any:
    """The campaign's engine told every scored run: the cached one told the new runs, or a new one."""
    from bac_campaign.report import refit_engine

    # each run with its outcomes: with outcome limits the model of each outcome is told as the agent's is
    runs = [(dict(t.params), float(t.j), dict(t.outcomes)) for t in camp.scored(include_confirmation=True)]
    cached = _ENGINES.get(key)
    if cached is not None:
        eng, told, options = cached
        if options == camp.engine_options and len(told) <= len(runs) and told == runs[: len(told)]:
            for params, j, outcomes in runs[len(told) :]:
                eng.tell(params, j, outcomes)  # as refit_engine tells them
            _ENGINES[key] = (eng, runs, options)
            return eng
    eng = refit_engine(camp)
    _ENGINES[key] = (eng, runs, camp.engine_options)
    return eng


def _r(values: Any, digits: int = 6) -> list[Any]:
    arr = np.asarray(values, dtype=float)
    if arr.ndim > 1:
        return [_r(row, digits) for row in arr]
    return [float(f"{v:.{digits}g}") if math.isfinite(v) else None for v in arr.tolist()]


def compute_model(campaign_dir: str | Path, grid: int = GRID) -> dict[str, Any]:
    """The GP view of the campaign in ``campaign_dir`` (JSON-able); ``status`` says why when there is none."""
    from bac_campaign.report import ReportError, load_campaign
    from bac_common.errors import BacError

    try:
        camp = load_campaign(campaign_dir)
    except ReportError as exc:
        return {"n_runs": 0, "status": f"no model: {exc}"}
    scored = camp.scored(include_confirmation=True)
    runs = [[t.trial_id, t.j] for t in scored]
    dims = list(camp.definition.dimensions)
    base: dict[str, Any] = {"n_runs": len(scored), "runs": runs, "names": [d.name for d in dims]}
    if camp.strategy != "bo":
        base["note"] = f"strategy {camp.strategy}: the model is fitted for the view only"
    if not scored:
        return {**base, "status": "no scored run yet: the model comes with the first J"}
    try:
        eng = _engine(camp, str(Path(campaign_dir).resolve()))
        final = camp.recommendation is not None
        if final:
            rec_params = dict(camp.recommendation["params"]) if camp.recommendation else {}
            rec_j = camp.recommendation.get("predicted_j") if camp.recommendation else None
            rec_std = camp.recommendation.get("predicted_std") if camp.recommendation else None
        else:
            r = eng.recommend()
            rec_params, rec_j, rec_std = dict(r.params), r.predicted_j, r.predicted_std
    except BacError as exc:
        return {**base, "status": f"no model: {exc}"}
    space = eng.space
    u_base = space.to_unit(space.to_array({**{d.name: (d.lower + d.upper) / 2 for d in dims}, **rec_params}))
    eng.predict_unit(u_base[None, :])  # fits the model: its lengthscales rank the dimensions
    hyper = eng.hyper
    ls = np.asarray(hyper.lengthscales, dtype=float) if hyper is not None else np.ones(len(dims))
    order = [int(i) for i in np.argsort(ls)] if len(dims) > 2 else list(range(len(dims)))
    shown = sorted(order[: min(2, len(dims))])
    out: dict[str, Any] = {
        **base,
        "status": f"GP posterior mean after {len(scored)} run{'s' if len(scored) != 1 else ''}",
        "dims": [{"name": dims[i].name, "lower": dims[i].lower, "upper": dims[i].upper} for i in shown],
        "lengthscales": {dims[i].name: finite_or_none(ls[i]) for i in range(len(dims))},
        "fixed": {dims[i].name: rec_params.get(dims[i].name) for i in range(len(dims)) if i not in shown},
        "recommendation": {
            "params": rec_params,
            "predicted_j": finite_or_none(rec_j),
            "predicted_std": finite_or_none(rec_std),
            "final": final,
        },
        "trials": [
            {"trial_id": t.trial_id, "params": dict(t.params), "j": finite_or_none(t.j), "kind": t.kind} for t in scored
        ],
        "failed": [{"trial_id": t.trial_id, "params": dict(t.params)} for t in camp.trials if t.status == "failed"],
    }
    if len(shown) == 1:
        i = shown[0]
        g = np.linspace(0.0, 1.0, 4 * grid)
        U = np.repeat(u_base[None, :], g.size, axis=0)
        U[:, i] = g
        m, s = eng.predict_unit(U)
        x = dims[i].lower + g * (dims[i].upper - dims[i].lower)
        out.update({"kind": "line", "x": _r(x), "mean": _r(m), "std": _r(s)})
        return out
    i, k = shown
    g = np.linspace(0.0, 1.0, grid)
    gx, gy = np.meshgrid(g, g)  # rows: the second dimension, columns: the first
    U = np.repeat(u_base[None, :], gx.size, axis=0)
    U[:, i] = gx.ravel()
    U[:, k] = gy.ravel()
    m, s = eng.predict_unit(U)
    out.update(
        {
            "kind": "contour",
            "x": _r(dims[i].lower + g * (dims[i].upper - dims[i].lower)),
            "y": _r(dims[k].lower + g * (dims[k].upper - dims[k].lower)),
            "mean": _r(m.reshape(grid, grid), 5),
            "std": _r(s.reshape(grid, grid), 3),
        }
    )
    return out
