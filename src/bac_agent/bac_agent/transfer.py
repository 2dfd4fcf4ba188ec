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
least 3 runs of a campaign reported becomes a surrogate built as J_mu is (a GP per campaign over its own runs, the
precision-weighted average of their posterior means, taken through this campaign's definition at Sobol points).
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

from bac_agent.bo.engine import EngineConfig, _one_blas_thread
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
    with _one_blas_thread():
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
            with _one_blas_thread():
                return outcome_sources_from_reduce_result(result, definition, names)
        return {}
    out = {}
    with _one_blas_thread():
        for name in dict.fromkeys(names):
            X, y, label = _campaign_runs(p, definition, outcome=name)
            if len(y) >= 3:
                out[name] = SourceSurface.fit(np.array(X), np.array(y), f"{name}: {label}", noisy=True)
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


def reduce_surrogate(data: dict[str, Any]) -> tuple[list[str], Callable[[FloatArray], FloatArray]]:
    """The raw parameter names of a reduce output's campaigns and J_mu over raw calibrations (n, P) in that order."""
    models = []
    names: list[str] | None = None
    for c in data.get("campaigns") or []:
        state = json.loads(c["engine_state"]) if isinstance(c["engine_state"], str) else dict(c["engine_state"])
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
    names, j_mu = reduce_surrogate(data)
    space = SearchSpace.from_definition(definition)
    probe = definition.expand(space.to_params(space.from_unit(np.full(space.dim, 0.5))))
    missing = [n for n in names if n not in probe]
    if missing:
        raise TransferError(
            f"the simulation phase in {result} calibrated {missing[:5]}..., which definition '{definition.name}' "
            "does not have: the prior must come from the same controller"
        )
    n = points or int(min(512, max(128, 64 * space.dim)))
    U = qmc.Sobol(space.dim, scramble=True, seed=seed).random(n)
    R = np.array([[definition.expand(space.to_params(space.from_unit(u)))[k] for k in names] for u in U])
    y = j_mu(R)
    if not np.all(np.isfinite(y)):
        raise TransferError(f"the surrogate of {result} is not finite everywhere in this campaign's space")
    m = len(data["campaigns"])
    return SourceSurface.fit(U, y, label=f"bac reduce {result} (J_mu of {m} campaigns, {n} points)")


def reduce_outcome_surrogate(
    data: dict[str, Any], name: str, seed: int = 0
) -> tuple[list[str], Callable[[FloatArray], FloatArray], int] | None:
    """The raw parameter names, the surrogate of outcome ``name`` over raw calibrations (n, P) and the runs it
    rests on: per campaign a GP (``NOISY_SOURCE_GP``: the runs are noisy) fitted to the runs that reported the
    outcome (at least 3), combined as J_mu is (precision-weighted posterior means); None when no campaign has one."""
    from bac_agent.bo.prior import NOISY_SOURCE_GP

    models = []
    names: list[str] | None = None
    runs = 0
    rng = np.random.default_rng(seed)
    for c in data.get("campaigns") or []:
        values = np.array([np.nan if v is None else float(v) for v in (c.get("outcomes") or {}).get(name, [])])
        X = np.asarray(c.get("X") or [], dtype=float)
        if values.size != X.shape[0] or int(np.sum(np.isfinite(values))) < 3:
            continue
        state = json.loads(c["engine_state"]) if isinstance(c["engine_state"], str) else dict(c["engine_state"])
        space = SearchSpace.from_dict(state["space"])
        ok = np.isfinite(values)
        gp = GP(NOISY_SOURCE_GP).fit(space.to_unit(X[ok]), values[ok], rng)
        models.append((space, gp))
        runs += int(np.sum(ok))
        names = list(space.names) if names is None else names
        if list(space.names) != names:
            raise TransferError("the campaigns of the reduce output tune different parameters")
    if not models or names is None:
        return None

    def surrogate(R: FloatArray) -> FloatArray:
        means, precisions = [], []
        for space, gp in models:
            m, sd = gp.predict(space.to_unit(R))
            means.append(m)
            precisions.append(1.0 / np.maximum(np.asarray(sd), 1e-12) ** 2)
        w = np.array(precisions)
        return np.asarray(np.sum(w * np.array(means), axis=0) / np.sum(w, axis=0), dtype=float)

    return names, surrogate, runs


def outcome_sources_from_reduce_result(
    result: Path, definition: CalibrationDefinition, outcomes: Sequence[str], points: int = 0, seed: int = 0
) -> dict[str, SourceSurface]:
    """What the simulation phase's runs reported of the ``outcomes`` (``reduce_outcome_surrogate``), each taken
    through ``definition`` at the Sobol points J_mu is taken at and fitted; an outcome no campaign reported on 3
    runs (or a result.json from before outcomes, schema 1) is left out."""
    data = _read_reduce_result(result)
    space = SearchSpace.from_definition(definition)
    n = points or int(min(512, max(128, 64 * space.dim)))
    U = qmc.Sobol(space.dim, scramble=True, seed=seed).random(n)
    out: dict[str, SourceSurface] = {}
    R_cache: dict[tuple[str, ...], FloatArray] = {}
    for name in dict.fromkeys(outcomes):
        got = reduce_outcome_surrogate(data, name, seed)
        if got is None:
            continue
        raw_names, f, runs = got
        key = tuple(raw_names)
        if key not in R_cache:
            _check_raw_names(result, definition, space, raw_names)
            R_cache[key] = np.array(
                [[definition.expand(space.to_params(space.from_unit(u)))[k] for k in raw_names] for u in U]
            )
        y = f(R_cache[key])
        if not np.all(np.isfinite(y)):
            raise TransferError(f"the {name} surrogate of {result} is not finite everywhere in this campaign's space")
        m = len(data["campaigns"])
        out[name] = SourceSurface.fit(
            U, y, label=f"{name}: bac reduce {result} ({runs} runs of {m} campaigns, {n} points)"
        )
    return out


def _read_reduce_result(result: Path) -> dict[str, Any]:
    try:
        data = json.loads(result.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise TransferError(f"cannot read {result}: {exc}") from exc
    if not isinstance(data, dict) or "campaigns" not in data:
        raise TransferError(f"{result} is not a bac reduce result.json (no campaigns)")
    version = int(data.get("schema_version", 1))
    if version > 2:
        raise TransferError(f"{result} has schema_version {version}: written by a newer bac (this one reads 1 and 2)")
    return data


def _check_raw_names(result: Path, definition: CalibrationDefinition, space: SearchSpace, names: list[str]) -> None:
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
