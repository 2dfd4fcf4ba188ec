"""``bac demo`` (``make demo``): the main job, a calibration campaign on the simulated vehicle.

It runs the real node graph of the ``sim`` profile (imu_ingest, run_segmenter,
kpi_scorer, campaign_recorder, bo_agent each in its own process; vehicle_sim
with its ECU and ecu_bridge sharing one, CAN on the in-process bus) on sim
time, faster than real time: Controller I on the speed bump with a budget of 15 trials (the
test road with ``--scenario road``). It shows the progress from the campaign
journal, then writes the report and judges the recommendation against the
simulator's true optimum; the last line reads ``recommendation_gap_pct <x>``
(x = 100 × (J(θ_rec) − J*) / (J_med − J*), with the true, noise-free J).

    bac demo [--scenario bump|road] [--budget 15] [--seed 0] [--with-grid] [--campaign-dir DIR] [--single-process]
             [--definition META_FILE [--truth-from RESULT_JSON]] [--visible] [--ecu bac|xcp]

The demo's graph runs in a private network namespace of its own (when one can be made), so that no other ROS
graph on the machine can disturb the campaign and its figures; ``--visible`` runs it in the machine's
namespace instead, where ROS tools (``ros2 topic echo /bac/trial``, rqt, Foxglove) see it, as
``bac launch sim`` does.

With ``--definition`` the campaign calibrates another definition, e.g. the meta-parameter file of
``bac reduce`` (the experimental phase of paper sec. III-D: Controller II on the test road, the
bridge expanding each meta-parameter into its raw parameters), and the gap is that space's own.
With ``--ecu xcp`` the simulated ECU is an XCP-on-CAN slave and the bridge calibrates it over XCP
(pyxcp), at the definition's A2L addresses: the same job through the protocol of a series ECU.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bac_bringup import netns
from bac_bringup.profile import workspace_dir
from bac_common.console import in_range

SCENARIOS = {
    # scenario: (simulated problem for the truth, extra parameter file, grid size of the baseline)
    "bump": ("bump_c1", None),
    "road": ("road_c1", "scenario_road.yaml"),
}


def out(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _fmt(params: dict[str, Any]) -> str:
    return " ".join(f"{k}={float(v):.3f}" for k, v in params.items())


class JournalFollower:
    """Prints a campaign's progress from its journal as the events arrive."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.pos = 0
        self.budget = 0
        self.best = math.inf
        self.best_trial = 0
        self.buf = b""

    def poll(self) -> None:
        try:
            with self.path.open("rb") as f:
                f.seek(self.pos)
                data = f.read()
        except FileNotFoundError:
            return
        self.pos += len(data)
        self.buf += data
        *lines, self.buf = self.buf.split(b"\n")
        for line in lines:
            if line.strip():
                self._show(json.loads(line))

    def _show(self, e: dict[str, Any]) -> None:
        kind = e.get("event")
        tid = e.get("trial_id")
        if kind == "campaign_started":
            self.budget = int(e.get("budget", 0))
            out(f"campaign {e.get('campaign_id')}: {', '.join(e.get('names', []))}, budget {self.budget} trials")
        elif kind == "trial_proposed":
            what = {
                0: "initial design",
                1: "max expected improvement",
                2: "confirmation of the recommendation",
                3: "grid point",
            }.get(int(e.get("kind", 1)), "")
            if e.get("reason") == "guess":
                what = "best guess: the simulation phase's optimum"
            out(f"  trial {tid}/{self.budget}: driving {_fmt(e.get('params', {}))}  ({what})")
        elif kind == "trial_scored":
            j = float(e["j"])
            if int(e.get("kind", 1)) != 2 and j < self.best:
                self.best, self.best_trial = j, int(tid or 0)
            out(f"  trial {tid}/{self.budget}: J = {j:.4f}   best so far {self.best:.4f} (trial {self.best_trial})")
        elif kind == "run_rejected":
            out(f"  trial {tid}: run {e.get('attempt')} rejected ({e.get('reason')}): driving it again")
        elif kind == "trial_failed":
            out(f"  trial {tid}: FAILED ({e.get('reason')})")
        elif kind == "recommendation":
            out(
                f"recommendation: {_fmt(e.get('params', {}))}, "
                f"predicted J {float(e.get('predicted_j') or math.nan):.4f}"
            )
        elif kind == "campaign_failed":
            out(f"campaign FAILED: {e.get('reason')}")


class CockpitAddress:
    """Prints the cockpit's address once its node has started (``<campaign>/cockpit.json``)."""

    def __init__(self, campaign_dir: Path) -> None:
        self.path = campaign_dir / "cockpit.json"
        self.path.unlink(missing_ok=True)  # left by a graph that did not stop cleanly: this launch writes its own
        self.shown = False

    def poll(self) -> None:
        if self.shown or not self.path.exists():
            return
        try:
            url = json.loads(self.path.read_text())["url"]
        except (OSError, ValueError, KeyError):
            return  # being written
        self.shown = True
        out(f"  cockpit: {url}  (open it in a browser: the page follows the campaign live; `bac watch` in a terminal)")


def run_campaign(
    campaign_dir: Path,
    params_files: list[Path],
    overrides: list[str],
    single_process: bool,
    timeout_s: float,
    private: bool = False,
) -> int:
    """Launch the sim profile in a child process and follow its journal; return the launcher's exit code.

    ``private``: the launcher runs in a private network namespace of its own (nothing else on the machine
    shares its ROS graph)."""
    cmd = [
        sys.executable,
        "-m",
        "bac_bringup.cli",
        "launch",
        "sim",
        "--campaign-dir",
        str(campaign_dir),
        "--log-dir",
        str(campaign_dir / "logs"),
        "--timeout",
        str(timeout_s),
    ]
    for f in params_files:
        cmd += ["--params-file", str(f)]
    for o in overrides:
        cmd += ["-p", o]
    if single_process:
        cmd.append("--single-process")
    env = None
    published = None
    if private and not netns.in_private_netns():
        # the cockpit's port inside the private namespace is out of the browser's reach: it is published here,
        # outside, on 127.0.0.1:8765 and relayed to the node through a Unix socket (bac_cockpit.relay)
        extra, published = publish_cockpit(params_files, overrides)
        cmd, env = netns.wrap_command(cmd + extra), netns.private_env()
    follower = JournalFollower(campaign_dir / "journal.jsonl")
    cockpit = CockpitAddress(campaign_dir)
    launcher_log = campaign_dir / "logs" / "launcher.log"
    launcher_log.parent.mkdir(parents=True, exist_ok=True)
    try:
        with launcher_log.open("wb") as log:
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
            try:
                while proc.poll() is None:
                    cockpit.poll()
                    follower.poll()
                    time.sleep(0.2)
            except KeyboardInterrupt:
                proc.send_signal(2)
                proc.wait()
                raise
    finally:
        if published is not None:
            published.close()
    follower.poll()
    return int(proc.returncode)


def publish_cockpit(params_files: list[Path], overrides: list[str]) -> tuple[list[str], Any]:
    """Start the relay of the sim profile's cockpit (its host and port from the profile's parameter files, the
    demo's and ``cockpit.*`` overrides); returns the launch's extra ``-p`` arguments and the relay."""
    from bac_bringup.cliargs import parse_assignment
    from bac_bringup.profile import load_profile
    from bac_cockpit.relay import publish_cockpit as publish

    files = [*load_profile("sim").params_files, *params_files]
    mine = {param: value for node, param, value in map(parse_assignment, overrides) if node == "cockpit"}
    return publish(files, mine)


def published_rates(log: Path) -> list[float]:
    """The real-time factor each run was published at, from vehicle_sim's log."""
    import re

    try:
        text = log.read_text(errors="replace")
    except OSError:
        return []
    return [float(x) for x in re.findall(r"of wall time, (\d+(?:\.\d+)?)x real time", text)]


def show_failure(campaign_dir: Path) -> None:
    logs = sorted(f for f in (campaign_dir / "logs").glob("*.log") if not f.is_symlink())  # a shared process: once
    for f in logs:
        lines = f.read_text(errors="replace").splitlines()
        bad = [x for x in lines if "ERROR" in x or "FATAL" in x or "Traceback" in x]
        if bad:
            out(f"--- {f.name} ---")
            out("\n".join(lines[-15:]))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="bac demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scenario", choices=sorted(SCENARIOS), default="bump", help="speed bump (default) or test road")
    ap.add_argument("--budget", type=in_range(int, 1, 10_000), default=15, help="trials of the BO campaign")
    ap.add_argument(
        "--seed", type=in_range(int, 0, 2**31 - 1), default=0, help="seed of the agent and of the simulated runs"
    )
    ap.add_argument("--with-grid", action="store_true", help="also run the 8x8 grid-search baseline through the graph")
    ap.add_argument(
        "--grid-size", type=in_range(int, 1, 100), default=8, help="grid points per parameter of the baseline"
    )
    ap.add_argument("--campaign-dir", type=Path, help="campaign folder (default: campaigns/demo-<scenario>-<time>)")
    ap.add_argument("--single-process", action="store_true", help="all nodes in one process (virtual CAN bus)")
    ap.add_argument("--timeout", type=float, default=900.0, help="give up after this many seconds")
    ap.add_argument(
        "--visible",
        action="store_true",
        help="run the graph in this machine's network namespace, where ROS tools see it (default: a private "
        "namespace of its own, so that no other ROS graph on the machine disturbs the campaign)",
    )
    ap.add_argument(
        "--definition",
        type=Path,
        help="calibration definition to calibrate instead of Controller I, e.g. the meta-parameter file of "
        "`bac reduce` (the experimental phase: Controller II on the test road, the bridge expands the "
        "meta-parameters); judged against that space's own optimum",
    )
    ap.add_argument(
        "--ecu",
        choices=("bac", "xcp"),
        default="bac",
        help="the simulated ECU's calibration protocol, and the bridge's: bac (default) or xcp (ASAM XCP on CAN)",
    )
    ap.add_argument(
        "--truth-from",
        type=Path,
        help="with --definition: the result.json of `bac reduce` holding the reduced optimum (else it is measured)",
    )
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))

    problem_name, extra = SCENARIOS[args.scenario]
    ws = workspace_dir()
    files = [ws / "params" / extra] if extra else []
    truth: Any = None
    definition_overrides: list[str] = []
    controller = "Controller I"
    if args.definition is not None:
        from bac_common.errors import BacError
        from bac_common.paramspace import CalibrationDefinition
        from bac_reduce.truth import definition_truth

        try:
            definition = CalibrationDefinition.load(args.definition.resolve())
        except (BacError, OSError, ValueError) as exc:
            out(f"bac demo: cannot load the definition {args.definition}: {exc}")
            return 2
        if len(definition.parameter_names) != 2:  # 2 raw parameters: Controller I through another definition
            if args.scenario != "road":
                out("bac demo: Controller II is simulated on the test road only: add --scenario road")
                return 2
            problem_name = "road_c2"
        d = args.definition.resolve()
        definition_overrides = [f"{n}.definition_file:={d}" for n in ("vehicle_sim", "ecu_bridge", "bo_agent")]
        dims = ", ".join(x.name for x in definition.dimensions)
        controller = f"{definition.name} ({len(definition.dimensions)} tuned: {dims})"
        out(f"bac demo: establishing the true optimum of {definition.name} on {problem_name} (noise-free simulator)")
        truth = definition_truth(definition, problem_name, args.truth_from, seed=args.seed)
        out(f"  J* {truth.j_star:.4f}, J_med {truth.j_med:.4f} ({truth.source})")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    camp = (args.campaign_dir or Path("campaigns") / f"demo-{args.scenario}-{stamp}").resolve()
    if (camp / "journal.jsonl").exists():
        out(f"bac demo: {camp} holds a campaign already: it is resumed")
    camp.mkdir(parents=True, exist_ok=True)
    seeds = [f"bo_agent.seed:={args.seed}", f"vehicle_sim.seed:={args.seed}"]
    where = "speed bump at 30 km/h" if args.scenario == "bump" else "1.5 km test road at 60 km/h"
    out(f"bac demo: {controller} on the simulated {where}")
    private = not args.visible
    if private and not netns.in_private_netns():
        try:
            netns.check_available()
        except netns.NetnsError as exc:
            out(f"bac demo: {exc}; the graph runs in this machine's network namespace")
            private = False
    layout = (
        "in one process"
        if args.single_process
        else "each in its own process, but vehicle_sim and ecu_bridge share one (CAN stays in it)"
    )
    ecu = "XCP" if args.ecu == "xcp" else "bac protocol"
    out(
        f"  the node graph: vehicle_sim (+ its {ecu} ECU on CAN), imu_ingest, run_segmenter, kpi_scorer, ecu_bridge, "
        f"campaign_recorder, cockpit, bo_agent, {layout}"
        + (", in a private network namespace (--visible: where ROS tools see it)" if private else "")
    )
    out(f"  campaign folder: {camp}")
    t0 = time.monotonic()
    protocol = [f"vehicle_sim.ecu_protocol:={args.ecu}", f"ecu_bridge.protocol:={args.ecu}"]
    overrides = [f"bo_agent.budget:={args.budget}", *seeds, *definition_overrides, *protocol]
    rc = run_campaign(camp, files, overrides, args.single_process, args.timeout, private)
    wall = time.monotonic() - t0
    if rc != 0 or not (camp / "recommendation.json").exists():
        out(f"bac demo: the campaign failed (launcher exit code {rc}); node logs in {camp / 'logs'}")
        show_failure(camp)
        page = _failure_report(camp, problem_name, truth)
        if page:
            out(f"report of what was driven: {page}")
        return rc or 1
    out(f"campaign done in {wall:.0f} s of wall time")
    rates = published_rates(camp / "logs" / "vehicle_sim.log")
    if rates:
        median = sorted(rates)[len(rates) // 2]
        out(
            f"  runs published at {min(rates):.1f}-{max(rates):.1f}x real time (median {median:.1f}x; "
            "vehicle_sim.log says why when a run fell short of the requested rate by more than 20 %)"
        )

    baseline = None
    if args.with_grid:
        baseline = camp.parent / f"{camp.name}-grid{args.grid_size}"
        n = args.grid_size**2
        out(f"bac demo: grid-search baseline, {args.grid_size}x{args.grid_size} = {n} trials through the same graph")
        t1 = time.monotonic()
        rc = run_campaign(
            baseline,
            files,
            [
                "bo_agent.strategy:=grid",
                f"bo_agent.grid_size:={args.grid_size}",
                f"bo_agent.budget:={n}",
                "bo_agent.confirmation_run:=false",
                *seeds,
                *definition_overrides,
                *protocol,
            ],
            args.single_process,
            args.timeout * 4,
            private,
        )
        if rc != 0:
            out(f"bac demo: the grid baseline failed (exit code {rc}); logs in {baseline / 'logs'}")
            show_failure(baseline)
            baseline = None
        else:
            out(f"grid baseline done in {time.monotonic() - t1:.0f} s")

    from bac_campaign.report import make_report

    result = make_report(camp, truth_name=problem_name, baseline_dir=baseline, truth=truth)
    s = result["summary"]
    rec = s["recommendation"]
    out("")
    out(f"recommendation: {_fmt(rec['params'])}")
    out(
        f"  predicted J {rec['predicted_j']:.4f} ± {rec['predicted_std']:.4f}; "
        f"true J {s['true_j_of_recommendation']:.4f} (true optimum J* {s['j_star']:.4f})"
    )
    if baseline is not None and result["baseline"]:
        b = result["baseline"]
        out(
            f"grid baseline: {b['trials']} trials, best observed J {b['best_observed_j']:.4f}, "
            f"gap of its best point {100 * b.get('gap_of_best_observed', math.nan):.1f} %"
        )
    if "runs_to_optimum" in s:
        r, r2 = s["runs_to_optimum"], s["runs_to_stay_found"]
        out(
            "  the recommendation came within gap 0.05 of the optimum "
            + (f"first after {r:.0f} runs" if math.isfinite(r) else "after none of the runs (not found)")
            + (f", for good after {r2:.0f} runs" if math.isfinite(r2) else "")
        )
    out(f"report: {result['html']}")
    out(f"cockpit of the finished campaign: bac cockpit {camp}")
    out(f"recommendation_gap_pct {100 * s['gap']:.2f}")
    return 0


def _failure_report(camp: Path, problem_name: str, truth: Any) -> str | None:
    """The report of a campaign that failed: what it drove, why it ended (never a traceback)."""
    from bac_campaign.report import make_report
    from bac_common.errors import BacError

    if not (camp / "journal.jsonl").exists():
        return None
    try:
        result = make_report(camp, truth_name=None if truth is not None else problem_name, truth=truth)
    except (BacError, OSError, ValueError) as exc:
        out(f"bac demo: no report either: {exc}")
        return None
    out(f"  {result['summary'].get('status', '')}")
    return str(result["html"])


if __name__ == "__main__":
    sys.exit(main())
