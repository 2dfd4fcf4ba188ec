"""bo_agent in a real process with a stand-in ECU bridge and a stand-in measurement chain."""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path
from typing import Any

import pytest

from bac_campaign.report import load_campaign

from conftest import wait_for

pytestmark = pytest.mark.integration

HERE = Path(__file__).resolve().parent
DEFN = HERE.parents[1] / "ros_ws" / "config" / "calibrations" / "controller_i.yaml"


def jsonl(path: Path) -> list[dict[str, Any]]:
    """The complete lines of a JSON-lines file that another process may be appending to right now."""
    if not path.exists():
        return []
    text = path.read_text()
    lines = text.split("\n")[:-1]  # a last piece without its newline is still being written
    return [json.loads(x) for x in lines if x.strip()]


def start_standins(procs: Any, tmp: Path, bridge_args: list[str] = (), chain_args: list[str] = ()) -> None:  # type: ignore[assignment]
    procs.python(
        "bridge",
        [str(HERE / "standins.py"), "bridge", "--ros-args", "-p", f"log_file:={tmp / 'bridge.jsonl'}", *bridge_args],
    )
    procs.python(
        "chain",
        [str(HERE / "standins.py"), "chain", "--ros-args", "-p", f"log_file:={tmp / 'chain.jsonl'}", *chain_args],
    )


def start_agent(procs: Any, name: str, cdir: Path, *params: str) -> Any:
    args = ["-m", "bac_agent.agent_node", "--ros-args", "-p", f"definition_file:={DEFN}", "-p", f"campaign_dir:={cdir}"]
    for p in params:
        args += ["-p", p]
    return procs.python(name, args)


def wait_exit(proc: Any, timeout: float, what: str) -> int:
    wait_for(lambda: proc.poll() is not None, timeout, what=what)
    return int(proc.returncode)


def check_scores_on_confirmed_calibrations(events: list[dict[str, Any]]) -> None:
    """Every trial_scored follows, in the same agent life, a successful apply of that trial."""
    confirmed: set[int] = set()
    for e in events:
        if e["event"] in ("campaign_started", "campaign_resumed"):
            confirmed = set()
        elif e["event"] == "apply_requested":
            confirmed.discard(e["trial_id"])
        elif e["event"] == "apply_result" and e["success"]:
            confirmed.add(e["trial_id"])
        elif e["event"] == "trial_scored":
            assert e["trial_id"] in confirmed, f"trial {e['trial_id']} scored on an unconfirmed calibration"


def test_campaign_runs_to_done_and_recommends(procs: Any, tmp_path: Path) -> None:
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path)
    agent = start_agent(
        procs,
        "agent",
        cdir,
        "budget:=5",
        "seed:=3",
        "confirmation_run:=true",
        "acquisition:=ei",
        "recommend_beta:=1.0",
        "gp_mean:=constant",
        "output_warp:=none",
        "design_margin:=0.1",
        "recommend_rule:=observed",
        "bowl_runs:=10",
    )
    assert wait_exit(agent, 90, "bo_agent to finish") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    # the optimizer's settings are journaled with the start, and the offline refit (bac report) reads them back
    start = next(e for e in ev if e["event"] == "campaign_started")
    assert (start["config"]["acquisition"], start["config"]["recommend_beta"]) == ("ei", 1.0)
    assert load_campaign(cdir).recommend_beta == 1.0
    assert start["config"]["gp_mean"] == "constant" and load_campaign(cdir).gp_mean == "constant"
    assert start["config"]["output_warp"] == "none" and load_campaign(cdir).engine_options["output_warp"] == "none"
    assert start["config"]["design_margin"] == 0.1
    assert start["config"]["bowl_runs"] == 10  # settable: campaigns from before the default moved to 6 resume
    # the recommendation rule (issue 23): journaled, followed (a driven calibration), read back by a refit, reported
    assert start["config"]["recommend_rule"] == "observed"
    assert load_campaign(cdir).engine_options["recommend_rule"] == "observed"
    (made,) = [e for e in ev if e["event"] == "recommendation"]
    assert made["rule"] == "observed"
    assert json.loads((cdir / "recommendation.json").read_text())["rule"] == "observed"
    driven = [e["params"] for e in ev if e["event"] == "trial_scored" and e["kind"] != 2]
    assert any(made["params"] == pytest.approx(p) for p in driven)
    from bac_campaign.report import make_report

    page = Path(make_report(cdir)["html"]).read_text()
    assert "recommendation rule" in page and "observed: the driven calibration with the best posterior mean" in page
    scored = [e for e in ev if e["event"] == "trial_scored"]
    assert [e["trial_id"] for e in scored] == [1, 2, 3, 4, 5, 6]  # 5 trials + the confirmation run
    assert scored[-1]["kind"] == 2
    chain = jsonl(tmp_path / "chain.jsonl")
    for e in scored:  # the J booked is the J the chain measured for that trial's calibration
        run = next(c for c in chain if c["trial_id"] == e["trial_id"] and c["attempt"] == e["attempt"])
        assert e["j"] == pytest.approx(run["j"])
        assert list(e["params"].values()) == pytest.approx(run["values"])
    rec = json.loads((cdir / "recommendation.json").read_text())
    assert set(rec["params"]) == {"damping_front", "damping_rear"}
    assert rec["confirmation_j"] == pytest.approx(scored[-1]["j"])
    for p in [e["params"] for e in ev if e["event"] == "trial_proposed"]:
        assert all(0.0 <= v <= 1.0 for v in p.values())  # asks never leave the bounds
    log = procs.log("agent")
    assert "trial 5/5 damping_front=" in log and "best=" in log
    check_scores_on_confirmed_calibrations(ev)


def test_invalid_run_repeated_and_failed_apply_never_scored(procs: Any, tmp_path: Path) -> None:
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path, ["-p", "fail_trials:='2'"], ["-p", "invalid_runs:='1:1,3:1,3:2'"])
    agent = start_agent(procs, "agent", cdir, "budget:=4", "max_attempts:=2", "apply_retries:=1")
    assert wait_exit(agent, 90, "bo_agent to finish") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    # trial 1: run 1 invalid, the same calibration driven again (run 2) and scored
    rej = [e for e in ev if e["event"] == "run_rejected"]
    assert [(e["trial_id"], e["attempt"]) for e in rej] == [(1, 1), (3, 1), (3, 2)]
    s1 = next(e for e in ev if e["event"] == "trial_scored" and e["trial_id"] == 1)
    assert s1["attempt"] == 2
    chain = jsonl(tmp_path / "chain.jsonl")
    t1 = [c for c in chain if c["trial_id"] == 1]
    assert len(t1) == 2 and t1[0]["values"] == t1[1]["values"]
    # trial 2: the ECU refused it twice; never driven, never scored, failed
    bridge = jsonl(tmp_path / "bridge.jsonl")
    assert [b["success"] for b in bridge if b["trial_id"] == 2] == [False, False]
    assert not [c for c in chain if c["trial_id"] == 2]
    assert not [e for e in ev if e["event"] in ("trial_scored", "run_ready") and e["trial_id"] == 2]
    f2 = next(e for e in ev if e["event"] == "trial_failed" and e["trial_id"] == 2)
    assert "ECU apply failed (error 3)" in f2["reason"]
    # trial 3: two invalid runs = max_attempts: failed
    assert any(e["event"] == "trial_failed" and e["trial_id"] == 3 for e in ev)
    assert [e["trial_id"] for e in ev if e["event"] == "trial_scored"] == [1, 4]
    check_scores_on_confirmed_calibrations(ev)


def test_resume_after_kill_9_loses_no_trial(procs: Any, tmp_path: Path) -> None:
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path, chain_args=["-p", "delay_s:=0.4"])
    agent = start_agent(procs, "agent1", cdir, "budget:=7", "seed:=5")
    journal = cdir / "journal.jsonl"
    wait_for(lambda: sum(e["event"] == "trial_scored" for e in jsonl(journal)) >= 3, 90, what="3 scored trials")
    os.killpg(agent.pid, signal.SIGKILL)
    agent.wait(timeout=10)
    before = jsonl(journal)
    scored_before = {e["trial_id"]: e["j"] for e in before if e["event"] == "trial_scored"}
    agent2 = start_agent(procs, "agent2", cdir, "budget:=7", "seed:=5")
    assert wait_exit(agent2, 120, "the restarted bo_agent to finish") == 0, procs.log("agent2")
    ev = jsonl(journal)
    assert ev[: len(before)] == before  # nothing rewritten
    assert sum(e["event"] == "campaign_resumed" for e in ev) == 1
    scored = [e for e in ev if e["event"] == "trial_scored"]
    assert sorted(e["trial_id"] for e in scored) == list(range(1, 8))  # every trial, each once
    for tid, j in scored_before.items():
        assert next(e["j"] for e in scored if e["trial_id"] == tid) == j
    assert "resumed" in procs.log("agent2")
    assert json.loads((cdir / "recommendation.json").read_text())["trials_done"] == 7
    check_scores_on_confirmed_calibrations(ev)


def test_a_resume_with_another_configuration_is_refused_at_start(procs: Any, tmp_path: Path) -> None:
    """Relaunched on a campaign folder with another seed and budget: the agent exits at once (the graph is not
    waited for), names both differences and says how to start a new campaign; the journal is untouched."""
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path)
    agent = start_agent(procs, "agent1", cdir, "budget:=2", "seed:=5")
    assert wait_exit(agent, 90, "bo_agent to finish") == 0, procs.log("agent1")
    before = (cdir / "journal.jsonl").read_bytes()
    agent2 = start_agent(procs, "agent2", cdir, "budget:=3", "seed:=6")
    assert wait_exit(agent2, 60, "the refusing bo_agent to exit") != 0
    log = procs.log("agent2")
    assert "seed: journaled 5, this agent 6" in log and "budget: journaled 2, this agent 3" in log, log
    assert "use a new campaign_dir" in log
    assert (cdir / "journal.jsonl").read_bytes() == before


def test_trial_1_waits_for_the_expected_readers_of_the_trial_topic(procs: Any, tmp_path: Path) -> None:
    cdir = tmp_path / "camp"
    procs.python("bridge", [str(HERE / "standins.py"), "bridge", "--ros-args", "-p",
                            f"log_file:={tmp_path / 'bridge.jsonl'}"])  # fmt: skip
    agent = start_agent(procs, "agent", cdir, "budget:=2", "expected_trial_subscribers:=1",
                        "subscriber_wait_s:=300.0")  # fmt: skip
    wait_for(lambda: "waiting for 1 readers of bac/trial" in procs.log("agent"), 60, what="the agent waiting")
    # nothing proposed, nothing applied while nobody listens to bac/trial (the bridge stand-in does not)
    assert not [e for e in jsonl(cdir / "journal.jsonl") if e["event"] == "trial_proposed"]
    assert not jsonl(tmp_path / "bridge.jsonl")
    procs.python("chain", [str(HERE / "standins.py"), "chain", "--ros-args", "-p",
                           f"log_file:={tmp_path / 'chain.jsonl'}"])  # fmt: skip
    assert wait_exit(agent, 120, "bo_agent to finish once a reader is there") == 0, procs.log("agent")
    chain = jsonl(tmp_path / "chain.jsonl")
    assert [c["trial_id"] for c in chain][:1] == [1]  # the reader saw trial 1 driven


def test_trial_1_waits_for_the_ecu_link_and_spends_no_trial_meanwhile(procs: Any, tmp_path: Path) -> None:
    """bac launch car without the CAN adapter: the agent burned 3 trials in 0.5 s and ended the campaign."""
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path, bridge_args=["-p", "link_down_s:=6.0"])
    agent = start_agent(procs, "agent", cdir, "budget:=2", "link_wait_s:=120.0")
    # the bridge's own reason, once its service is there (before, the agent says the service is not available)
    wait_for(
        lambda: "no link to the ECU yet (cannot open CAN interface" in procs.log("agent"),
        60,
        what="the agent telling why it waits",
    )
    assert "is the adapter plugged in" in procs.log("agent")
    assert not [e for e in jsonl(cdir / "journal.jsonl") if e["event"] == "trial_proposed"]
    assert not [b for b in jsonl(tmp_path / "bridge.jsonl") if not b.get("read")]  # nothing applied
    assert wait_exit(agent, 120, "bo_agent to finish once the link is up") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    assert not [e for e in ev if e["event"] == "trial_failed"]
    assert [b["success"] for b in jsonl(tmp_path / "bridge.jsonl") if not b.get("read")][:1] == [True]


def test_no_ecu_link_at_all_stops_before_spending_a_trial(procs: Any, tmp_path: Path) -> None:
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path, bridge_args=["-p", "link_down_s:=1000.0"])
    agent = start_agent(procs, "agent", cdir, "budget:=2", "link_wait_s:=3.0")
    assert wait_exit(agent, 60, "bo_agent to give up waiting") == 2, procs.log("agent")
    assert "No ECU link after 3 s" in procs.log("agent")
    assert not [e for e in jsonl(cdir / "journal.jsonl") if e["event"] == "trial_proposed"]


def test_a_link_lost_mid_campaign_pauses_it_and_fails_no_trial(procs: Any, tmp_path: Path) -> None:
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path, bridge_args=["-p", "bus_down_trial:=2", "-p", "bus_down_applies:=4"])
    agent = start_agent(procs, "agent", cdir, "budget:=3", "apply_retries:=0", "link_retry_s:=0.2")
    assert wait_exit(agent, 120, "bo_agent to finish") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    assert not [e for e in ev if e["event"] == "trial_failed"]
    assert [e["trial_id"] for e in ev if e["event"] == "link_lost"] == [2]
    bus = [b for b in jsonl(tmp_path / "bridge.jsonl") if b.get("bus")]
    assert [b["trial_id"] for b in bus] == [2, 2, 2, 2]
    assert len([e for e in ev if e["event"] == "trial_scored"]) == 3


def test_a_transfer_prior_and_an_outcome_limit_through_the_node_and_the_report(procs: Any, tmp_path: Path) -> None:
    """issue 23: prior_source (an earlier campaign's folder) and constraints, journaled, modelled, reported."""
    from standins import known_j, known_peak

    from bac_agent.journal import Journal
    from bac_campaign.report import make_report

    source = tmp_path / "earlier"
    j = Journal(source)
    j.append("campaign_started", campaign_id="earlier", names=["damping_front", "damping_rear"], stamp=0.0)
    k = 0
    for a in (0.1, 0.3, 0.5, 0.7, 0.9):
        for b in (0.2, 0.5, 0.8):
            k += 1
            j.append(
                "trial_scored",
                campaign_id="earlier",
                trial_id=k,
                params={"damping_front": a, "damping_rear": b},
                j=2.0 + 1.5 * known_j([a, b]),
                outcomes={"peak_accel_z": known_peak([a, b]) + 0.3},  # the earlier car peaked a little higher
                stamp=float(k),
            )
    j.close()
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path)
    agent = start_agent(
        procs,
        "agent",
        cdir,
        "budget:=6",
        "seed:=1",
        f"prior_source:={source}",
        "constraints:=['peak_accel_z<=6.0']",
    )
    assert wait_exit(agent, 120, "bo_agent to finish") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    start = next(e for e in ev if e["event"] == "campaign_started")
    assert start["config"]["constraints"] == ["peak_accel_z<=6.0"]
    assert start["config"]["prior_summary"]["label"].startswith("campaign earlier (15 runs")
    assert start["config"]["prior"]["X"]  # the surface itself, so that a refit models as the agent did
    # the earlier campaign's measured peaks are the prior of the limited peak's model
    assert start["config"]["outcome_priors"]["peak_accel_z"]["label"].startswith("peak_accel_z: campaign earlier")
    assert "outcome priors: peak_accel_z: campaign earlier (15 runs)" in procs.log("agent")
    proposed = [e for e in ev if e["event"] == "trial_proposed"]
    # trial 1: the prior's best calibration whose peak the earlier campaign's peaks allow (its optimum, near
    # (0.3, 0.6), peaks at 6.2 > 6.0)
    assert proposed[0]["reason"] == "prior"
    assert known_peak(list(proposed[0]["params"].values())) <= 6.0
    assert proposed[0]["params"]["damping_front"] > 0.4
    assert any("transfer" in e.get("model", {}) for e in proposed[1:])
    scored = [e for e in ev if e["event"] == "trial_scored"]
    for e in scored:  # outcomes are booked with every run; a run that broke the limit says so
        peak = known_peak(list(e["params"].values()))
        assert e["outcomes"] == pytest.approx({"peak_accel_z": peak})
        assert bool(e["violations"]) == (peak > 6.0)
    rec = json.loads((cdir / "recommendation.json").read_text())
    assert known_peak(list(rec["params"].values())) <= 6.0
    assert rec["predicted_outcomes"]["peak_accel_z <= 6"]["p_violation_true"] <= 0.05
    assert "transfer_weight" in rec["transfer"]
    assert "outcome limits: peak_accel_z<=6.0" in procs.log("agent")
    out = make_report(cdir)
    figures = [Path(f).name for f in out["figures"]]
    assert "prior_posterior.png" in figures
    page = Path(out["html"]).read_text()
    assert "peak_accel_z" in page and "transfer prior at the end" in page
    broken = [e["trial_id"] for e in scored if e["violations"]]
    assert out["summary"]["limit_breaking_trials"] == broken

    # a campaign started before outcome priors existed (its journal has neither key) resumes as it ran: the
    # source's measured peaks do not become a prior it never had (the outside review: it was refused, and no
    # parameter could turn the priors off)
    lines = (cdir / "journal.jsonl").read_text().splitlines()
    first = json.loads(lines[0])
    assert first["event"] == "campaign_started"
    for key in ("outcome_priors", "prior_runs", "prior_average"):
        del first["config"][key]
    (cdir / "journal.jsonl").write_text("\n".join([json.dumps(first), *lines[1:]]) + "\n")
    agent2 = start_agent(
        procs,
        "agent2",
        cdir,
        "budget:=6",
        "seed:=1",
        f"prior_source:={source}",
        "prior_average:=false",  # it ran the model with the prior alone (before prior_average)
        "constraints:=['peak_accel_z<=6.0']",
    )
    assert wait_exit(agent2, 120, "the resumed bo_agent to finish") == 0, procs.log("agent2")
    assert "cannot resume" not in procs.log("agent2")


def test_a_safe_start_drives_the_baseline_first_and_grows_within_the_limit(procs: Any, tmp_path: Path) -> None:
    """issue 23: with constraints and nothing known of the outcome, safe_start makes trial 1 the definition's
    baseline (journaled), the next runs within the limit and a safe step; a journal from before the safe start
    resumes as it ran."""
    from standins import known_peak

    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path)
    # (limit_trend_far and limit_reach act on nothing with a safe start: given here to see them reach the journal)
    params = (
        "budget:=5",
        "seed:=2",
        "constraints:=['peak_accel_z<=6.0']",
        "safe_start:=true",
        "limit_trend_far:=0.2",
        "limit_reach:=0.2",  # not the default 0.15: the journal must show the parameter reached the engine
    )
    agent = start_agent(procs, "agent", cdir, *params)
    assert wait_exit(agent, 120, "bo_agent to finish") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    start = next(e for e in ev if e["event"] == "campaign_started")
    baseline = {"damping_front": 0.5, "damping_rear": 0.5}  # controller_i.yaml's baseline
    assert start["config"]["safe_start"] == baseline
    assert start["config"]["limit_trend_far"] == 0.2 and start["config"]["limit_reach"] == 0.2
    proposed = [e for e in ev if e["event"] == "trial_proposed"]
    assert proposed[0]["reason"] == "safe" and proposed[0]["params"] == baseline
    scored = [e for e in ev if e["event"] == "trial_scored"]
    assert len(scored) == 5
    # every run (the design grown from the safe start, then the acquisition's: SafeOpt's safe set for the whole
    # campaign since 2026-11-24; before, the acquisition's 4th run broke the limit) keeps the limit, each a safe
    # step (SAFE_STEP 0.25) at most from an earlier run that kept it; a run that broke it would be booked as such
    runs = [e["params"] for e in proposed]
    assert len([e for e in proposed if e["reason"] in ("safe", "initial")]) >= 2
    assert any(e["reason"] == "optimized" for e in proposed)
    assert all(known_peak(list(q.values())) <= 6.0 for q in runs), [known_peak(list(q.values())) for q in runs]
    for i, q in enumerate(runs[1:], start=1):
        step = min(sum((q[n] - r[n]) ** 2 for n in ("damping_front", "damping_rear")) ** 0.5 for r in runs[:i])
        assert step <= 0.25 + 1e-6, (q, runs[:i])
    assert all(bool(e["violations"]) == (e["outcomes"]["peak_accel_z"] > 6.0) for e in scored)

    lines = (cdir / "journal.jsonl").read_text().splitlines()
    first = json.loads(lines[0])
    del first["config"]["safe_start"]
    (cdir / "journal.jsonl").write_text("\n".join([json.dumps(first), *lines[1:]]) + "\n")
    agent2 = start_agent(procs, "agent2", cdir, *params)
    assert wait_exit(agent2, 120, "the resumed bo_agent to finish") == 0, procs.log("agent2")
    assert "cannot resume" not in procs.log("agent2")


def test_a_simulation_phase_output_gives_the_limited_outcomes_priors_through_the_node(
    procs: Any, tmp_path: Path
) -> None:
    """issue 23: prior_source names a bac reduce output whose runs reported the simulator's travel (result.json
    schema 2): the agent builds the travel limit's prior from them, logs and journals it, and trial 1 is the
    phase's best calibration whose travel keeps the limit (its J optimum, soft front dampers, does not)."""
    import numpy as np
    from standins import known_j

    from bac_agent.bo import Engine, EngineConfig
    from bac_common.paramspace import CalibrationDefinition

    def travel(u: np.ndarray) -> np.ndarray:  # the simulator's: soft front dampers travel far (80 mm at 0)
        u = np.atleast_2d(u)
        return np.asarray(80.0 - 40.0 * u[:, 0])

    definition = CalibrationDefinition.load(DEFN)
    campaigns = []
    for seed in (0, 1):
        eng = Engine(definition, EngineConfig(budget=10, seed=seed))
        X, y = [], []
        for _ in range(10):
            q = eng.ask()
            x = [q["damping_front"], q["damping_rear"]]
            eng.tell(q, known_j(x))
            X.append(x)
            y.append(known_j(x))
        eng.recommend()
        state = json.loads(eng.to_json())
        assert state.get("hyper")
        campaigns.append(
            {"X": X, "y": y, "engine_state": eng.to_json(), "outcomes": {"max_travel_mm": travel(np.array(X)).tolist()}}
        )
    out = tmp_path / "reduce_out"
    out.mkdir()
    (out / "result.json").write_text(json.dumps({"schema_version": 2, "campaigns": campaigns}))
    cdir = tmp_path / "camp"
    start_standins(procs, tmp_path)
    agent = start_agent(
        procs, "agent", cdir, "budget:=2", "seed:=1", f"prior_source:={out}", "constraints:=['max_travel_mm<=60']"
    )
    assert wait_exit(agent, 120, "bo_agent to finish") == 0, procs.log("agent")
    ev = jsonl(cdir / "journal.jsonl")
    start = next(e for e in ev if e["event"] == "campaign_started")
    label = start["config"]["outcome_priors"]["max_travel_mm"]["label"]
    assert label.startswith("max_travel_mm: bac reduce") and "20 runs of 2 campaigns" in label
    assert "outcome priors: max_travel_mm: bac reduce" in procs.log("agent")
    first = next(e for e in ev if e["event"] == "trial_proposed")
    assert first["reason"] == "prior"
    # the J optimum (0.3, 0.6) travels 68 mm: trial 1 is where the phase's travel keeps the limit
    assert first["params"]["damping_front"] > 0.5


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
