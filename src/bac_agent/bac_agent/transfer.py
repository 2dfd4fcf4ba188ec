"""Where a transfer prior comes from: a ``bac reduce`` output or an earlier campaign, as a :class:`SourceSurface`.

``bo_agent``'s ``prior_source`` names one of

* **a ``bac reduce`` output** (its folder or its ``result.json``): the simulation phase's surrogate J_mu, the
  precision-weighted average of its M campaigns' posterior means (what the phase's sensitivity analysis used;
  ``bac_reduce.pipeline.PosteriorMean``), evaluated through this campaign's calibration definition: each point
  of the campaign's unit cube is expanded to the full raw calibration (meta-parameters, fixed values) and J_mu
  is taken there. The definition may be the meta-parameter file the phase wrote, or any other over the same raw
  parameters;
* **a campaign folder** (its ``journal.jsonl``): the runs an earlier campaign scored (on the simulated car, on
  another car, on this car last season), over the same tuned dimensions by name; runs outside this campaign's
  bounds are left out.

What the source knows of a **limited outcome** (``load_outcome_sources``; issue 23): an earlier campaign's runs
carry their measured outcomes (``max_travel_mm``, ``peak_accel_z``, ...); each outcome this campaign limits and
at least 3 of those runs measured becomes a source surface of that outcome, the prior of its model
(``EngineConfig.outcome_priors``). A ``bac reduce`` output (``result.json`` schema 2, since 2026-11-24) stores
what each simulated run reported besides J (``max_travel_mm``, ``lift_off_ms``): each limited outcome that at
least 3 runs reported becomes a source fitted to those runs as a campaign folder's are (noisy runs), pooled over
the phase's campaigns and placed in this campaign's space through its definition (``project_runs``; since
2026-11-24 evening: before, a dense noise-free sample of a surrogate, certain also where the phase never ran).
An older result.json (J only) gives none, and the car's outcome models then start from their first runs.

Either becomes a :class:`~bac_agent.bo.prior.SourceSurface` over this campaign's unit cube (a GP fitted to
``points`` Sobol samples of J_mu, or to the runs themselves), which the engine uses as its transfer prior
(``EngineConfig.prior``). bac_reduce depends on bac_agent, not the other way round: the few lines that rebuild
a reduce campaign's posterior from its stored engine state are repeated here.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import qmc

from bac_agent.bo.blas import one_blas_thread
from bac_agent.bo.engine import EngineConfig
from bac_agent.bo.gp import GP, Hyper
from bac_agent.bo.prior import SourceSurface
from bac_agent.bo.space import SearchSpace
from bac_agent.bo.warp import OutputWarp
from bac_agent.journal import JOURNAL_NAME, read_journal
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition

FloatArray = NDArray[np.float64]
REDUCE_RESULT = "result.json"


class TransferError(BacError, ValueError):
    """A transfer prior's source cannot be used (not found, other parameters, too few runs)."""


def load_source(path: str | Path, definition: CalibrationDefinition, points: int = 0, seed: int = 0) -> SourceSurface:
    """The source surface of a ``bac reduce`` output or a campaign folder, over ``definition``'s tuned space.

    ``points``: Sobol samples of a reduce surrogate (0: 64 per dimension, 128 to 512). Fitted with one BLAS thread,
    as the engine fits: the same files give the same surface bit for bit in every process, so that a resumed agent
    rebuilds the surface its journal holds (a resume compares them: ``Campaign.check_resume``).
    """
    p = Path(path).expanduser()
    with one_blas_thread():
        if p.is_dir() and (p / JOURNAL_NAME).is_file():
            return from_campaign(p, definition)
        result = p / REDUCE_RESULT if p.is_dir() else p
        if result.is_file() and result.suffix == ".json":
            return from_reduce_result(result, definition, points, seed)
    raise TransferError(
        f"prior_source {str(path)!r} is neither a bac reduce output (a folder with {REDUCE_RESULT}, or that file) "
        f"nor a campaign folder (with {JOURNAL_NAME})"
    )


def load_outcome_sources(
    path: str | Path, definition: CalibrationDefinition, names: Sequence[str]
) -> dict[str, SourceSurface]:
    """What the source at ``path`` knows of the outcomes ``names`` (those this campaign limits): a campaign
    folder's runs of each outcome that at least 3 runs within the bounds measured, fitted over ``definition``'s
    tuned space; a ``bac reduce`` output scores J only and gives none (an empty mapping)."""
    p = Path(path).expanduser()
    if not names:
        return {}
    if not (p.is_dir() and (p / JOURNAL_NAME).is_file()):
        result = p / REDUCE_RESULT if p.is_dir() else p
        if result.is_file() and result.suffix == ".json":
            with one_blas_thread():
                return outcome_sources_from_reduce_result(result, definition, names)
        return {}
    out = {}
    with one_blas_thread():
        for name in dict.fromkeys(names):
            X, y, label = _campaign_runs(p, definition, outcome=name)
            if len(y) >= 3:
                out[name] = SourceSurface.fit(np.array(X), np.array(y), f"{name}: {label}", noisy=True, outcome=True)
    return out


def _campaign_runs(
    folder: Path, definition: CalibrationDefinition, outcome: str | None = None
) -> tuple[list[FloatArray], list[float], str]:
    """The unit-cube points and values (J, or the measured ``outcome``) of an earlier campaign's scored runs within
    ``definition``'s bounds, and a label."""
    events = read_journal(folder / JOURNAL_NAME).events
    if not events or events[0].get("event") != "campaign_started":
        raise TransferError(f"{folder / JOURNAL_NAME} does not start with campaign_started: not a campaign journal")
    space = SearchSpace.from_definition(definition)
    theirs = [str(n) for n in events[0].get("names", [])]
    if sorted(theirs) != sorted(space.names):
        raise TransferError(
            f"the campaign in {folder} tuned {theirs}, this campaign tunes {list(space.names)}: "
            "a campaign folder can be a prior only for the same tuned dimensions"
        )
    X, y, outside = [], [], 0
    for e in events:
        if e.get("event") != "trial_scored" or e.get("j") is None:
            continue
        value = e.get("j") if outcome is None else (e.get("outcomes") or {}).get(outcome)
        if value is None or not np.isfinite(float(value)):
            continue
        x = np.array([float(e["params"][n]) for n in space.names])
        u = space.to_unit(x)
        if np.any(u < -1e-9) or np.any(u > 1 + 1e-9):
            outside += 1
            continue
        X.append(np.clip(u, 0.0, 1.0))
        y.append(float(value))
    label = f"campaign {events[0].get('campaign_id', folder.name)} ({len(y)} runs"
    label += f", {outside} outside the bounds left out)" if outside else ")"
    return X, y, label


def from_campaign(folder: Path, definition: CalibrationDefinition) -> SourceSurface:
    """The scored runs of an earlier campaign, fitted over ``definition``'s tuned space."""
    X, y, label = _campaign_runs(folder, definition)
    if len(y) < 3:
        raise TransferError(
            f"the campaign in {folder} has {len(y)} scored runs within this campaign's bounds: a prior needs at least 3"
        )
    return SourceSurface.fit(np.array(X), np.array(y), label, noisy=True)


def reduce_surrogate(
    data: dict[str, Any], result: Path = Path(REDUCE_RESULT)
) -> tuple[list[str], Callable[[FloatArray], FloatArray]]:
    """The raw parameter names of a reduce output's campaigns and J_mu over raw calibrations (n, P) in that order."""
    models = []
    names: list[str] | None = None
    for k, c in enumerate(data.get("campaigns") or []):
        state = _engine_state(result, k, c)
        if not state.get("hyper"):
            continue
        space = SearchSpace.from_dict(state["space"])
        cfg = EngineConfig.from_dict(state["config"])
        X = np.asarray(c["X"], dtype=float)
        y = np.asarray(c["y"], dtype=float)
        warp = OutputWarp.for_runs(cfg.output_warp, y)
        gp = GP(cfg.gp).condition(space.to_unit(X), warp.forward(y), Hyper.from_dict(state["hyper"]))
        models.append((space, gp, warp))
        names = list(space.names) if names is None else names
        if list(space.names) != names:
            raise TransferError("the campaigns of the reduce output tune different parameters")
    if not models or names is None:
        raise TransferError("the reduce output has no campaign with a fitted model")

    def j_mu(R: FloatArray) -> FloatArray:
        means, precisions = [], []
        for space, gp, warp in models:
            m, sd = warp.inverse_mean_std(*gp.predict(space.to_unit(R)))
            means.append(m)
            precisions.append(1.0 / np.maximum(np.asarray(sd), 1e-12) ** 2)
        w = np.array(precisions)
        return np.asarray(np.sum(w * np.array(means), axis=0) / np.sum(w, axis=0), dtype=float)

    return names, j_mu


def from_reduce_result(
    result: Path, definition: CalibrationDefinition, points: int = 0, seed: int = 0
) -> SourceSurface:
    """The simulation phase's J_mu through ``definition``, sampled at Sobol points and fitted."""
    data = _read_reduce_result(result)
    names, j_mu = reduce_surrogate(data, result)
    space = SearchSpace.from_definition(definition)
    _check_raw_names(result, definition, space, names)
    n = points or int(min(512, max(128, 64 * space.dim)))
    U = qmc.Sobol(space.dim, scramble=True, seed=seed).random(n)
    R = np.array([[definition.expand(space.to_params(space.from_unit(u)))[k] for k in names] for u in U])
    y = j_mu(R)
    if not np.all(np.isfinite(y)):
        raise TransferError(f"the surrogate of {result} is not finite everywhere in this campaign's space")
    m = len(data["campaigns"])
    return SourceSurface.fit(U, y, label=f"bac reduce {result} (J_mu of {m} campaigns, {n} points)")


def _engine_state(result: Path, k: int, c: Any) -> dict[str, Any]:
    """Campaign ``k``'s stored engine state (its search space, its model)."""
    if not isinstance(c, dict) or "engine_state" not in c:
        raise TransferError(
            f"campaign {k + 1} of {result} has no engine_state: the file is damaged or was not written by "
            "bac reduce; write it again with bac reduce"
        )
    raw = c["engine_state"]
    try:
        state = json.loads(raw) if isinstance(raw, str) else dict(raw)
        SearchSpace.from_dict(state["space"])
    except (TypeError, ValueError, KeyError) as exc:
        raise TransferError(f"campaign {k + 1} of {result}: unreadable engine_state ({exc!r})") from exc
    return state


def project_runs(definition: CalibrationDefinition, names: Sequence[str], R: FloatArray) -> FloatArray:
    """Raw calibrations ``R`` (n, P; columns ``names``) seen in ``definition``'s tuned space (n, d): a raw
    dimension its value, a meta-parameter its members' mean position in their ranges (``baseline_tuned``'s rule:
    the nearest point of the meta-parameter's line in the members' relative coordinates); NaN where a tuned raw
    dimension is not among ``names``. Values outside the definition's bounds are kept (the caller leaves them out)."""
    col = {n: i for i, n in enumerate(names)}
    R = np.atleast_2d(np.asarray(R, dtype=float))
    out = np.full((R.shape[0], len(definition.dimensions)), np.nan)
    for j, d in enumerate(definition.dimensions):
        if not d.is_meta:
            if d.name in col:
                out[:, j] = R[:, col[d.name]]
            continue
        m = definition.meta_parameter(d.name)
        if not all(n in col for n in m.members):
            continue
        rel = [(R[:, col[n]] - p.lower) / (p.upper - p.lower) for n in m.members for p in (definition.parameter(n),)]
        out[:, j] = m.lower + np.mean(rel, axis=0) * (m.upper - m.lower)
    return out


def reduce_outcome_runs(
    result: Path, data: dict[str, Any], definition: CalibrationDefinition, name: str
) -> tuple[FloatArray, FloatArray, str]:
    """The simulation phase's runs that reported outcome ``name``, pooled over its campaigns and seen in
    ``definition``'s unit cube (``project_runs``), their values and a label; runs outside the bounds left out."""
    space = SearchSpace.from_definition(definition)
    Xs, ys, used, outside = [], [], 0, 0
    for k, c in enumerate(data.get("campaigns") or []):
        listed = (c.get("outcomes") or {}).get(name)
        if listed is None:
            continue
        X = np.asarray(c.get("X") or [], dtype=float)
        try:
            values = np.array([np.nan if v is None else float(v) for v in listed], dtype=float)
        except (TypeError, ValueError) as exc:
            raise TransferError(f"campaign {k + 1} of {result}: {name} holds a value that is not a number") from exc
        if values.size != X.shape[0]:
            raise TransferError(
                f"campaign {k + 1} of {result} has {X.shape[0]} runs but {values.size} values of {name}: the file "
                "is damaged or was edited by hand; write it again with bac reduce (or remove that outcome)"
            )
        ok = np.isfinite(values)
        if not np.any(ok):
            continue
        state = _engine_state(result, k, c)
        raw_names = list(SearchSpace.from_dict(state["space"]).names)
        _check_raw_names(result, definition, space, raw_names)
        T = project_runs(definition, raw_names, X[ok])
        if np.any(np.isnan(T)):
            missing = [d.name for j, d in enumerate(definition.dimensions) if np.isnan(T[0, j])]
            raise TransferError(
                f"the simulation phase in {result} did not calibrate {missing}, which definition "
                f"'{definition.name}' tunes: its runs cannot be placed in this campaign's space"
            )
        U = space.to_unit(T)
        inside = np.all((U >= -1e-9) & (U <= 1 + 1e-9), axis=1)
        outside += int(np.sum(~inside))
        used += 1
        Xs.append(np.clip(U[inside], 0.0, 1.0))
        ys.append(values[ok][inside])
    X_all = np.vstack(Xs) if Xs else np.zeros((0, space.dim))
    y_all = np.concatenate(ys) if ys else np.zeros(0)
    label = f"bac reduce {result} ({y_all.size} runs of {used} campaigns"
    label += f", {outside} outside the bounds left out)" if outside else ")"
    return X_all, y_all, label


def outcome_sources_from_reduce_result(
    result: Path, definition: CalibrationDefinition, outcomes: Sequence[str]
) -> dict[str, SourceSurface]:
    """What the simulation phase's runs reported of the ``outcomes``: each outcome's runs, pooled over the
    campaigns and placed in ``definition``'s unit cube (``reduce_outcome_runs``), fitted as noisy runs, as a
    campaign folder's are (``load_outcome_sources``); an outcome fewer than 3 runs reported (or a result.json from
    before outcomes, schema 1) is left out.

    Why the runs and not J_mu's way (a surrogate sampled densely at Sobol points): a GP fitted to a dense sample of
    a model's means is certain everywhere (its posterior variance is round-off), also far from every run of a phase
    whose BO campaigns clustered near their optima; the runs carry what the phase did not see into the source's
    own variance (``bo.constraints``: C_s), as a campaign folder's runs do (outside review, 2026-11-24)."""
    data = _read_reduce_result(result)
    out: dict[str, SourceSurface] = {}
    for name in dict.fromkeys(outcomes):
        X, y, label = reduce_outcome_runs(result, data, definition, name)
        if y.size < 3:
            continue
        out[name] = SourceSurface.fit(X, y, f"{name}: {label}", noisy=True, outcome=True)
    return out


def _read_reduce_result(result: Path) -> dict[str, Any]:
    try:
        data = json.loads(result.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise TransferError(f"cannot read {result}: {exc}") from exc
    if not isinstance(data, dict) or "campaigns" not in data:
        raise TransferError(f"{result} is not a bac reduce result.json (no campaigns)")
    raw_version = data.get("schema_version", 1)
    if isinstance(raw_version, bool) or not isinstance(raw_version, int | float) or raw_version != int(raw_version):
        raise TransferError(
            f"{result} has schema_version {raw_version!r}, not a whole number: the file is damaged or was not "
            "written by bac reduce"
        )
    version = int(raw_version)
    if version > 2:
        raise TransferError(f"{result} has schema_version {version}: written by a newer bac (this one reads 1 and 2)")
    return data


def _check_raw_names(result: Path, definition: CalibrationDefinition, space: SearchSpace, names: list[str]) -> None:
    """The simulation phase's raw parameter names must all be the definition's (the same controller)."""
    probe = definition.expand(space.to_params(space.from_unit(np.full(space.dim, 0.5))))
    missing = [n for n in names if n not in probe]
    if missing:
        raise TransferError(
            f"the simulation phase in {result} calibrated {missing[:5]}..., which definition '{definition.name}' "
            "does not have: the prior must come from the same controller"
        )


def summary(source: SourceSurface, space: SearchSpace) -> dict[str, Any]:
    """What the journal and the report show of a source: where it came from, its optimum and its range."""
    u = source.argmin()
    lo_hi = source.predict_j(np.vstack([u[None, :], qmc.Sobol(space.dim, scramble=True, seed=1).random(256)]))
    return {
        "label": source.label,
        "points": int(source.X.shape[0]),
        "optimum": space.to_params(space.from_unit(u)),
        "optimum_j": float(lo_hi[0]),
        "j_range": [float(np.min(lo_hi)), float(np.max(lo_hi))],
        "noisy": bool(source.noisy),
    }


__all__ = [
    "REDUCE_RESULT",
    "TransferError",
    "from_campaign",
    "from_reduce_result",
    "load_outcome_sources",
    "load_source",
    "outcome_sources_from_reduce_result",
    "summary",
]
