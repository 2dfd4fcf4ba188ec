"""Latency of one ask() with 100 observations in 20 dimensions, hyperparameter fit included (issue 5).

Each repetition builds a fresh engine, tells it 100 noisy observations of a
20-dimensional test function (Controller II's size) and times one ``ask()``,
which fits the GP hyperparameters from scratch (no warm start) and maximizes log
EI. The baseline measured in the same run is one GP fit + prediction of the same
data by scikit-learn's GaussianProcessRegressor (Matérn-5/2 ARD + noise, 2
restarts), for scale. With ``--botorch`` (needs ``scripts/setup.sh --bench``) it
also times BoTorch's SingleTaskGP fit + qLogNEI optimize_acqf on the same data.

The same ask is also timed with a transfer prior (a source surface fitted to 256 Sobol points of a shifted
copy of the test function, bo/prior.py) and two outcome limits (each of the 100 runs carries two outcomes):
``ask_s_n100_d20_prior_2limits``, goal <= 0.3 s (issue 23); and with each limited outcome's prior too
(``EngineConfig.outcome_priors``, 256 points each): ``ask_s_n100_d20_prior_2limits_outcome_priors``.

LAST lines: ``ask_s_n100_d20 <median seconds>`` (goal <= 0.2 s on this machine), then
``ask_s_n100_d20_prior_2limits <median seconds>``.

    .venv/bin/python bench/agent_latency.py [--reps 7] [--botorch]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings

import numpy as np

N, D = 100, 20


def data(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.random((N, D))
    y = np.sum((X - 0.3) ** 2 * np.linspace(0.2, 2.0, D), axis=1) + np.sin(5 * X[:, 0]) + 0.05 * rng.standard_normal(N)
    return X, y


_SOURCE: dict[int, object] = {}


def source_dict() -> object:
    """The transfer prior of the latency test (fitted once per process, as the agent fits it once at its start)."""
    if 0 not in _SOURCE:
        from scipy.stats import qmc

        from bac_agent.bo.prior import SourceSurface

        U = qmc.Sobol(D, scramble=True, seed=0).random(256)
        y = np.sum((U - 0.35) ** 2 * np.linspace(0.2, 2.0, D), axis=1) + np.sin(5 * U[:, 0])
        _SOURCE[0] = SourceSurface.fit(U, y, "latency test").to_dict()
    return _SOURCE[0]


def outcome_sources() -> dict[str, object]:
    """The two limited outcomes' priors (256 Sobol points each of a shifted copy of what the runs measure): what
    the simulator knows of them (EngineConfig.outcome_priors, issue 23)."""
    if 1 not in _SOURCE:
        from scipy.stats import qmc

        from bac_agent.bo.prior import SourceSurface

        U = qmc.Sobol(D, scramble=True, seed=1).random(256)
        _SOURCE[1] = {
            "peak_accel_z": SourceSurface.fit(U, 1.1 + U[:, 0] - 0.4 * U[:, 1], "latency test").to_dict(),
            "max_travel_mm": SourceSurface.fit(U, 52.0 + 18.0 * U[:, 2], "latency test").to_dict(),
        }
    return _SOURCE[1]  # type: ignore[return-value]


def time_bac(seed: int, prior_and_limits: bool = False, outcome_priors: bool = False) -> float:
    from bac_agent.bo import Engine, EngineConfig

    X, y = data(seed)
    cfg = EngineConfig(budget=200, n_initial=10, seed=seed)
    if prior_and_limits:
        cfg = EngineConfig(
            budget=200,
            n_initial=10,
            seed=seed,
            prior=source_dict(),  # type: ignore[arg-type]
            constraints=("peak_accel_z<=1.5", "max_travel_mm<=60"),
            outcome_priors=outcome_sources() if outcome_priors else None,
        )
    eng = Engine([(f"p{i:02d}", 0.0, 1.0) for i in range(D)], cfg)
    names = eng.names
    for x, v in zip(X, y, strict=True):
        outcomes = {"peak_accel_z": 1.0 + x[0] - 0.5 * x[1], "max_travel_mm": 50.0 + 20.0 * x[2]}
        eng.tell(dict(zip(names, x.tolist(), strict=True)), float(v), outcomes if prior_and_limits else None)
    t0 = time.perf_counter()
    p = eng.ask()
    dt = time.perf_counter() - t0
    assert all(0.0 <= p[n] <= 1.0 for n in names)
    return dt


def time_sklearn(seed: int) -> float:
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    X, y = data(seed)
    k = ConstantKernel() * Matern(length_scale=np.ones(D), nu=2.5) + WhiteKernel(1e-2)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = GaussianProcessRegressor(k, normalize_y=True, n_restarts_optimizer=2, random_state=seed).fit(X, y)
    gp.predict(np.random.default_rng(seed).random((1024, D)), return_std=True)
    return time.perf_counter() - t0


def time_botorch(seed: int) -> float:
    import torch
    from botorch.acquisition.logei import qLogNoisyExpectedImprovement
    from botorch.fit import fit_gpytorch_mll
    from botorch.models import SingleTaskGP
    from botorch.models.transforms import Standardize
    from botorch.optim import optimize_acqf
    from gpytorch.mlls import ExactMarginalLogLikelihood

    X, y = data(seed)
    Xt = torch.tensor(X)
    Yt = -torch.tensor(y).unsqueeze(-1)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = SingleTaskGP(Xt, Yt, outcome_transform=Standardize(1))
        fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
        acq = qLogNoisyExpectedImprovement(model, X_baseline=Xt)
        bounds = torch.stack([torch.zeros(D), torch.ones(D)]).to(torch.double)
        optimize_acqf(acq, bounds=bounds, q=1, num_restarts=10, raw_samples=512)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--botorch", action="store_true", help="also time BoTorch (benchmark dependencies)")
    a = ap.parse_args(argv)
    time_bac(100)  # warm-up: imports, BLAS threads
    ours = [time_bac(s) for s in range(a.reps)]
    time_bac(100, True)
    with_prior = [time_bac(s, True) for s in range(a.reps)]
    time_bac(100, True, True)
    with_outcome_priors = [time_bac(s, True, True) for s in range(a.reps)]
    base = [time_sklearn(s) for s in range(a.reps)]
    m_ours, m_base = statistics.median(ours), statistics.median(base)
    print(f"# {a.reps} repetitions, n={N} observations, d={D} dimensions, medians")
    print(
        f"bac ask (fit from scratch + log-NEI maximization): {m_ours:.3f} s  (min {min(ours):.3f}, max {max(ours):.3f})"
    )
    print(f"sklearn GPR fit (2 restarts) + predict 1024:      {m_base:.3f} s")
    print(f"ratio bac / sklearn: {m_ours / m_base:.2f}")
    if a.botorch:
        time_botorch(100)
        bt = [time_botorch(s) for s in range(a.reps)]
        m_bt = statistics.median(bt)
        print(
            f"botorch fit + qLogNEI optimize_acqf:             {m_bt:.3f} s  (ratio bac / botorch {m_ours / m_bt:.2f})"
        )
    m_prior = statistics.median(with_prior)
    print(
        f"bac ask with a transfer prior and two outcome limits: {m_prior:.3f} s  (min {min(with_prior):.3f}, "
        f"max {max(with_prior):.3f})"
    )
    m_op = statistics.median(with_outcome_priors)
    print(
        f"bac ask with a transfer prior and two outcome limits with their priors: {m_op:.3f} s  "
        f"(min {min(with_outcome_priors):.3f}, max {max(with_outcome_priors):.3f})"
    )
    print(f"ask_s_n100_d20_prior_2limits_outcome_priors {m_op:.4f}")
    print(f"ask_s_n100_d20 {m_ours:.4f}")
    print(f"ask_s_n100_d20_prior_2limits {m_prior:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
