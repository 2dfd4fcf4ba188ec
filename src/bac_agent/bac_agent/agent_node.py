"""``bo_agent``: runs a calibration campaign (paper algorithm 1) through the graph.

A thin node around :class:`bac_agent.campaign.Campaign`: it converts messages,
declares the parameters (what they build, the optimizer and the campaign's
configuration, is :func:`bac_agent.agent_setup.build_agent`, pure Python), and
executes the campaign's actions:

* ``Publish``  → ``bac/trial`` (bac_msgs/Trial, latched);
* ``Apply``    → ``ecu_bridge/apply_calibration`` called asynchronously, waited for
  with a time limit (the service's appearance too), never blocking a callback;
* ``AwaitRun`` → a run deadline in ROS time (sim time under ``use_sim_time``);
* ``Finish``   → ``self.finish(code)`` (the launcher ends the graph).

Scores come from ``bac/run_score`` (bac_msgs/RunScore). Everything the node
does runs in one mutually exclusive callback group (a 20 Hz steady-clock tick
polls the pending service call and the deadlines), so the campaign sees one
event at a time.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from typing import Any

from builtin_interfaces.msg import Time as TimeMsg
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.duration import Duration

from bac_agent.agent_setup import (
    BACKSTOP_RUN_TIMEOUT_S,
    START_FROM,
    STRATEGIES,
    AgentSettings,
    build_agent,
    make_verifier,
)
from bac_agent.bo.engine import ACQUISITIONS, RULES
from bac_agent.bo.gp import MEANS
from bac_agent.bo.warp import WARPS
from bac_agent.campaign import (
    Action,
    Apply,
    AwaitRun,
    Campaign,
    Finish,
    Kind,
    Log,
    Publish,
    State,
    TrialStatus,
)
from bac_common.contracts import SRV_APPLY_CALIBRATION, SRV_READ_CALIBRATION, TOPIC_RUN_SCORE, TOPIC_TRIAL
from bac_common.errors import BacError
from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED, BacNode, run_node
from bac_msgs.msg import Calibration, RunScore, Trial
from bac_msgs.srv import ApplyCalibration, ReadCalibration

FINAL_ACK_S = 2.0  # the longest the agent waits at the end for subscribers to acknowledge the last bac/trial


class BoAgentNode(BacNode):
    """The campaign agent (see the module doc and docs/agent.md)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("bo_agent", **kwargs)
        D = AgentSettings()  # the parameters' defaults: one place for the node and build_agent
        definition_file = self.declare_str(
            "definition_file",
            D.definition_file,
            "calibration definition (YAML path, or the name of a shipped definition)",
            read_only=True,
        )
        campaign_dir = self.declare_str(
            "campaign_dir", D.campaign_dir, "campaign folder: journal.jsonl, recommendation.json", read_only=True
        )
        campaign_id = self.declare_str(
            "campaign_id",
            D.campaign_id,
            "campaign id carried by every run (default: the campaign folder's name)",
            read_only=True,
        )
        self.strategy = self.declare_str(
            "strategy", D.strategy, "how calibrations are chosen", choices=STRATEGIES, read_only=True
        )
        budget = self.declare_int("budget", D.budget, "trials of the campaign (bo, random)", 1, 10_000, read_only=True)
        n_initial = self.declare_int(
            "n_initial",
            D.n_initial,
            "space-filling initial trials (0 = automatic: 5 for d <= 4, else d + 1)",
            0,
            1000,
            True,
        )
        seed = self.declare_int("seed", D.seed, "random seed of the optimizer", 0, 2**31 - 1, read_only=True)
        acquisition = self.declare_str(
            "acquisition",
            D.acquisition,
            "bo: how the next calibration is chosen (nei: noisy expected improvement, ei: EI over the best mean)",
            choices=ACQUISITIONS,
            read_only=True,
        )
        recommend_beta = self.declare_float(
            "recommend_beta",
            D.recommend_beta,
            "bo: the recommendation minimizes posterior mean + beta * std (0: the paper's argmin of the mean)",
            0.0,
            5.0,
            read_only=True,
        )
        recommend_rule = self.declare_str(
            "recommend_rule",
            D.recommend_rule,
            "bo: the recommendation is the argmin of the posterior mean over the box (mean: the paper, the best on "
            "the tuning split), the driven calibration with the best posterior mean (observed) or with the best "
            "measured J (best_run); with outcome limits always within them",
            choices=RULES,
            read_only=True,
        )
        gp_mean = self.declare_str(
            "gp_mean",
            D.gp_mean,
            "bo: the GP's prior mean (bowl: a bowl-shaped trend for the first runs, then a constant; constant; zero)",
            choices=MEANS,
            read_only=True,
        )
        bowl_runs = self.declare_int(
            "bowl_runs",
            D.bowl_runs,
            "bo with gp_mean bowl: runs the bowl-shaped trend lasts (0 = automatic: the initial design + 1; "
            "campaigns started before 2026-11-24 07:15 used twice the initial design: set it to resume them)",
            0,
            1000,
            read_only=True,
        )
        gp_bowl_loo = self.declare_bool(
            "gp_bowl_loo",
            D.gp_bowl_loo,
            "bo with gp_mean bowl: keep the bowl only while it predicts the runs, left out one at a time, better "
            "than a constant mean (from 2d + 1 runs, at least 5); false: as before 2026-11-24 (late)",
            True,
        )
        gp_ls_average = self.declare_float(
            "gp_ls_average",
            D.gp_ls_average,
            "bo: the GP is fitted under two lengthscale priors, of sd 1 and of this sd (tighter, median sqrt(2) both), "
            "and the noisy EI and the posterior mean are averaged over the two fits (0: one fit, as before "
            "2026-11-25; a campaign journaled without it resumes without it)",
            0.0,
            0.99,
            read_only=True,
        )
        face_explore = self.declare_int(
            "face_explore",
            D.face_explore,
            "bo: exploration along the faces after a stall: when the recommendation lies on a face of the box (a "
            "parameter at a bound) and the last this many runs lie within 0.2 (unit cube) of it, the next run is the "
            "most uncertain calibration on the faces through it, 0.2 or more from every run (0: off, as before "
            "2026-11-25; a campaign journaled without it resumes without it)",
            0,
            100,
            read_only=True,
        )
        output_warp = self.declare_str(
            "output_warp",
            D.output_warp,
            "bo: the GP sees the runs through a fitted Yeo-Johnson transform (yeo-johnson) or as told (none)",
            choices=WARPS,
            read_only=True,
        )
        design_margin = self.declare_float(
            "design_margin",
            D.design_margin,
            "bo: the initial design spans [m, 1 - m] of every parameter's range (0: the whole range)",
            0.0,
            0.49,
            read_only=True,
        )
        start_from = self.declare_str(
            "start_from",
            D.start_from,
            "bo: guess = the first trial is the definition's best_guess when it has one (the simulation phase's "
            "optimum, written by bac reduce; the paper's best-guess initialization), then the initial design; "
            "design = the initial design alone",
            choices=START_FROM,
            read_only=True,
        )
        prior_source = self.declare_str(
            "prior_source",
            D.prior_source,
            "bo: a transfer prior: a bac reduce output (its folder or result.json: the simulation phase's surrogate "
            "through this definition) or an earlier campaign's folder (its runs); its optimum is the first trial and "
            "its shape the model's prior mean while the runs support it; with constraints, what its runs reported "
            "of each limited outcome is that outcome's prior ('' = none)",
            read_only=True,
        )
        prior_weight = self.declare_float(
            "prior_weight",
            D.prior_weight,
            "bo: prior probability that the transfer prior describes this car",
            0.01,
            0.99,
            True,
        )
        prior_runs = self.declare_int(
            "prior_runs",
            D.prior_runs,
            "bo with prior_source: runs told up to which the prior's shape may be the model's prior mean, then the "
            "car's runs alone (0 = no limit: as long as the runs support it)",
            0,
            1000,
            read_only=True,
        )
        prior_average = self.declare_bool(
            "prior_average",
            D.prior_average,
            "bo with prior_source: while the runs support the prior, the acquisition averages the models with and "
            "without it by the transfer weight (false: the model with the prior alone, as before 2026-11-24)",
            True,
        )
        prior_average_ls = self.declare_bool(
            "prior_average_ls",
            D.prior_average_ls,
            "bo with prior_source and gp_ls_average > 0: in that average the model without the prior is itself "
            "averaged over its fits under both lengthscale priors, as the model without a prior is (false: one fit, "
            "as before 2026-11-25, and a campaign journaled without it resumes without it)",
            True,
        )
        constraints = self.declare_str_list(
            "constraints",
            list(D.constraints),
            "limits on what a run measures besides J, e.g. peak_accel_z<=6.5 (RunScore outcomes): bo never "
            "proposes a calibration likely to break one (constraint_level) and recommends within them; a run "
            "that breaks one is booked and shown",
            read_only=True,
        )
        constraint_level = self.declare_float(
            "constraint_level",
            D.constraint_level,
            "bo: the largest probability of breaking an outcome limit a proposal or the recommendation may have",
            0.001,
            0.5,
            read_only=True,
        )
        safe_start = self.declare_bool(
            "safe_start",
            D.safe_start,
            "bo with constraints: trial 1 is the definition's baseline (the ECU's reference calibration, assumed to "
            "keep the limits) and the initial design grows from it within what the outcome models allow (only while "
            "a limited outcome has no prior)",
            True,
        )
        limit_trend = self.declare_bool(
            "limit_trend",
            D.limit_trend,
            "bo with constraints: during the initial design a calibration is proposed only when the outcome's model "
            "with a linear trend allows it too, and the least risky calibration (when none is within "
            "constraint_level) is judged by that model (no effect with safe_start or when every limit has an outcome "
            "prior); false: as before 2026-11-25, and a campaign journaled without it resumes without it",
            True,
        )
        limit_far_sd = self.declare_float(
            "limit_far_sd",
            D.limit_far_sd,
            "bo with constraints: far from the runs each limited outcome's model (without an outcome prior) is "
            "widened, its sd multiplied by 1 + limit_far_sd * (its posterior variance over its kernel's variance); "
            "0: off, and a campaign journaled without it resumes without it",
            0.0,
            10.0,
            read_only=True,
        )
        limit_trend_far = self.declare_float(
            "limit_trend_far",
            D.limit_trend_far,
            "bo with constraints and limit_trend (opt-in): after the initial design a calibration farther than this "
            "(unit cube, Euclidean) from every run is proposed only when the outcome's model with a linear trend "
            "allows it too (no effect with safe_start or when every limit has an outcome prior); 0: off, and a "
            "campaign journaled without it resumes without it",
            0.0,
            10.0,
            read_only=True,
        )
        limit_reach = self.declare_float(
            "limit_reach",
            D.limit_reach,
            "bo with constraints: after the initial design a proposal lies within this distance times sqrt(d/2) "
            "(unit cube, Euclidean; d tuned parameters) of a run that kept every limit, once one has; an ask where "
            "it leaves nothing within constraint_level goes without it (no effect with safe_start or outcome "
            "priors); 0: off, and a campaign journaled without it resumes without it",
            0.0,
            10.0,
            read_only=True,
        )
        grid_size = self.declare_int(
            "grid_size", D.grid_size, "levels per dimension of the grid strategy", 1, 100, True
        )
        max_attempts = self.declare_int("max_attempts", D.max_attempts, "runs per trial before it is given up", 1, 100)
        apply_timeout = self.declare_float(
            "apply_timeout_s", D.apply_timeout_s, "time limit of one apply, s", 0.1, 600.0
        )
        apply_retries = self.declare_int(
            "apply_retries", D.apply_retries, "further apply tries after a failed one", 0, 20
        )
        self.expected_trial_subscribers = self.declare_int(
            "expected_trial_subscribers",
            0,
            "readers of bac/trial (the recorder, the segmenter, a simulated car...) to wait for before the first "
            "trial, so that none misses it while discovery between processes is still going on (0: do not wait)",
            0,
            100,
        )
        self.subscriber_wait_s = self.declare_float(
            "subscriber_wait_s", 30.0, "longest wait for expected_trial_subscribers, then start anyway, s", 0.0, 3600.0
        )
        self.service_wait_s = self.declare_float(
            "service_wait_s", 15.0, "how long to wait for the ECU bridge's service to appear, s", 0.1, 3600.0
        )
        run_timeout = self.declare_float(
            "run_timeout_s",
            D.run_timeout_s,
            "ROS time from READY_TO_DRIVE to a score before the run counts invalid, s; 0 = the measurement chain "
            f"decides (run_segmenter's run timeout, derived from the segment) and the agent waits at most "
            f"{BACKSTOP_RUN_TIMEOUT_S:g} s (a dead chain)",
            0.0,
            1e6,
        )
        confirmation = self.declare_bool(
            "confirmation_run", D.confirmation_run, "drive the recommendation once more before DONE"
        )
        max_failures = self.declare_int(
            "max_consecutive_failures",
            D.max_consecutive_failures,
            "failed trials in a row that end the campaign",
            1,
            1000,
        )
        busy_retry = self.declare_float(
            "busy_retry_s", D.busy_retry_s, "wait before asking a busy ECU (vehicle moving) again, s", 0.05, 600.0
        )
        busy_timeout = self.declare_float(
            "busy_timeout_s",
            D.busy_timeout_s,
            "ROS time an ECU may stay busy before the apply counts as failed, s",
            0.0,
            1e6,
        )
        self.link_wait_s = self.declare_float(
            "link_wait_s",
            120.0,
            "before trial 1, wait this long for the ECU link (ecu_bridge/read_calibration answering), telling the "
            "driver why on bac/trial; then stop without having spent a trial, s (0: do not wait)",
            0.0,
            86400.0,
        )
        link_retry = self.declare_float(
            "link_retry_s",
            D.link_retry_s,
            "the ECU link is down (ERROR_BUS): ask again after this long, paused, s",
            0.05,
            600.0,
        )
        link_timeout = self.declare_float(
            "link_timeout_s",
            D.link_timeout_s,
            "ROS time the ECU link may stay down mid-campaign (paused, no trial fails) before the campaign stops, "
            "resumable, s",
            0.0,
            1e6,
        )
        resume = self.declare_bool(
            "resume", D.resume, "continue the campaign in campaign_dir's journal (false: refuse an existing one)", True
        )

        settings = AgentSettings(
            definition_file=definition_file,
            campaign_dir=campaign_dir,
            campaign_id=campaign_id,
            strategy=self.strategy,
            budget=budget,
            n_initial=n_initial,
            seed=seed,
            acquisition=acquisition,
            recommend_beta=recommend_beta,
            recommend_rule=recommend_rule,
            gp_mean=gp_mean,
            bowl_runs=bowl_runs,
            gp_bowl_loo=gp_bowl_loo,
            gp_ls_average=gp_ls_average,
            face_explore=face_explore,
            output_warp=output_warp,
            design_margin=design_margin,
            start_from=start_from,
            prior_source=prior_source,
            prior_weight=prior_weight,
            prior_runs=prior_runs,
            prior_average=prior_average,
            prior_average_ls=prior_average_ls,
            constraints=tuple(constraints),
            constraint_level=constraint_level,
            safe_start=safe_start,
            limit_trend=limit_trend,
            limit_far_sd=limit_far_sd,
            limit_trend_far=limit_trend_far,
            limit_reach=limit_reach,
            grid_size=grid_size,
            max_attempts=max_attempts,
            apply_timeout_s=apply_timeout,
            apply_retries=apply_retries,
            run_timeout_s=run_timeout,
            confirmation_run=confirmation,
            max_consecutive_failures=max_failures,
            busy_retry_s=busy_retry,
            busy_timeout_s=busy_timeout,
            link_retry_s=link_retry,
            link_timeout_s=link_timeout,
            resume=resume,
        )
        setup = build_agent(settings)  # the pure part: definition, journal, optimizer, configuration
        self.definition = setup.definition
        journal = setup.journal
        self.campaign = Campaign(
            setup.optimizer,
            journal,
            setup.config,
            clock=lambda: self.get_clock().now().nanoseconds * 1e-9,
            definition=self.definition.to_dict(),
            verify_applied=make_verifier(self.definition),
        )
        try:
            # a journal of another configuration is refused now, before the graph waits for anything
            changed = self.campaign.check_resume()
        except BacError as exc:
            journal.close()
            self.get_logger().error(str(exc))
            raise
        if changed:
            self.get_logger().warning("resuming with other time limits than journaled: " + "; ".join(changed))
        self._lock = threading.Lock()
        self._group = MutuallyExclusiveCallbackGroup()
        self.pub_trial = self.create_publisher(Trial, TOPIC_TRIAL, QOS_LATCHED)
        self.client = self.create_client(ApplyCalibration, SRV_APPLY_CALIBRATION, callback_group=self._group)
        self.read_client = self.create_client(ReadCalibration, SRV_READ_CALIBRATION, callback_group=self._group)
        self.sub_score = self.create_subscription(
            RunScore, TOPIC_RUN_SCORE, self._on_score, QOS_EVENTS, callback_group=self._group
        )
        # pending work polled by the tick
        self._apply: Apply | None = None
        self._apply_future: Any = None
        self._apply_deadline = 0.0  # monotonic
        self._apply_started = 0.0
        self._run: AwaitRun | None = None
        self._run_deadline_ns = 0  # ROS time
        self._started = False
        self._wait_since: float | None = None
        self._link = _LinkWait()
        self._tick = self.create_timer(
            0.05, self._on_tick, callback_group=self._group, clock=Clock(clock_type=ClockType.STEADY_TIME)
        )
        for line in setup.log_lines():
            self.get_logger().info(line)
        for line in setup.resumed_as_journaled:
            self.get_logger().warning(line)

    # --- actions ----------------------------------------------------------------------------------
    def _do(self, actions: list[Action]) -> None:
        for a in actions:
            if isinstance(a, Publish):
                self.pub_trial.publish(self._trial_msg(a.status))
            elif isinstance(a, Apply):
                self._apply = a
                self._apply_future = None
                self._apply_started = time.monotonic() + a.delay_s  # not called before then
                self._apply_deadline = self._apply_started + self.service_wait_s
                self._run = None
            elif isinstance(a, AwaitRun):
                self._run = a
                self._run_deadline_ns = self.get_clock().now().nanoseconds + int(a.timeout_s * 1e9)
            elif isinstance(a, Log):
                # rclpy refuses one call site logging at several severities: one call per level
                if a.level == "error":
                    self.get_logger().error(a.text)
                elif a.level == "warn":
                    self.get_logger().warning(a.text)
                else:
                    self.get_logger().info(a.text)
            elif isinstance(a, Finish):
                self._apply = None
                self._run = None
                self.campaign.journal.close()
                # the campaign's last state reaches every subscriber before the launcher ends the graph: the
                # recorder, the cockpit, a `ros2 topic echo` apart from the launcher (a CI run's listener missed
                # STATE_DONE once: the agent had finished before the message was delivered)
                if not self.pub_trial.wait_for_all_acked(Duration(seconds=FINAL_ACK_S)):
                    self.get_logger().warning(
                        "bac/trial: not every subscriber acknowledged the campaign's last state within "
                        f"{FINAL_ACK_S:g} s"
                    )
                self.finish(a.code)

    def _trial_msg(self, s: TrialStatus) -> Trial:
        m = Trial()
        ns = int(s.stamp * 1e9) if math.isfinite(s.stamp) else 0
        m.stamp = TimeMsg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        m.campaign_id = s.campaign_id
        m.trial_id = int(s.trial_id)
        m.attempt = int(s.attempt)
        m.state = int(s.state)
        m.kind = int(s.kind)
        m.calibration = Calibration(
            trial_id=int(s.trial_id), names=list(s.params), values=[float(v) for v in s.params.values()]
        )
        m.budget = int(s.budget)
        m.trials_done = int(s.trials_done)
        m.last_j = float(s.last_j)
        m.best_j = float(s.best_j)
        m.best_trial_id = int(s.best_trial_id)
        m.predicted_j = float(s.predicted_j)
        m.predicted_j_std = float(s.predicted_j_std)
        m.instruction = s.instruction
        m.reason = s.reason
        return m

    # --- callbacks ----------------------------------------------------------------------------------
    def _on_tick(self) -> None:
        with self._lock:
            if self.exit_code is not None:
                return
            if not self._started:
                if not self._readers_ready() or not self._link_ready():
                    return
                self._started = True
                self._do(self.campaign.start())
                return
            self._poll_apply()
            self._poll_run()

    def _readers_ready(self) -> bool:
        """True when bac/trial has its expected readers, or when waiting for them took too long (with a warning)."""
        need = self.expected_trial_subscribers
        have = self.pub_trial.get_subscription_count()
        if have >= need:
            return True
        now = time.monotonic()
        if self._wait_since is None:
            self._wait_since = now
            self.get_logger().info(f"waiting for {need} readers of {TOPIC_TRIAL} before trial 1 ({have} so far)")
        if now - self._wait_since < self.subscriber_wait_s:
            return False
        self.get_logger().warning(
            f"{have} of {need} expected readers of {TOPIC_TRIAL} after {self.subscriber_wait_s:g} s "
            "(is the whole graph running?): starting anyway"
        )
        return True

    def _link_ready(self) -> bool:
        """True once the bridge reads the ECU (the link works); until then bac/trial says why the campaign waits.

        Bounded by ``link_wait_s``: then the node finishes with code 2 before a single trial was spent.
        """
        w = self._link
        if self.link_wait_s <= 0 or w.ok:
            return True
        now = time.monotonic()
        if w.since is None:
            w.since = now
            self.get_logger().info(f"waiting for the ECU link ({SRV_READ_CALIBRATION}) before trial 1")
        if w.future is not None:
            if not w.future.done():
                if now - w.asked < 30.0:
                    return False
                self.read_client.remove_pending_request(w.future)
                w.problem = f"{SRV_READ_CALIBRATION} did not answer within 30 s"
            else:
                try:
                    res = w.future.result()
                except Exception as exc:  # the call itself failed (the service went away)
                    res, w.problem = None, f"reading the ECU failed: {exc}"
                if res is not None and res.success:
                    w.ok = True
                    self.get_logger().info(f"ECU link up: the bridge reads the ECU ({now - w.since:.1f} s)")
                    return True
                if res is not None:
                    w.problem = str(res.message) or "the bridge could not read the ECU"
            w.future = None
        elif not self.read_client.service_is_ready():
            w.problem = f"service {SRV_READ_CALIBRATION} not available (is ecu_bridge running?)"
        if now - w.since > self.link_wait_s:
            text = (
                f"No ECU link after {self.link_wait_s:g} s: {w.problem}. The campaign did not start and no trial was "
                "spent; fix the link (is the adapter plugged in and its interface up?) and launch again."
            )
            self.get_logger().error(text)
            self.pub_trial.publish(self._waiting_msg(text, w.problem))
            self.campaign.journal.close()
            self.finish(2)
            return False
        if w.problem and w.problem != w.told:
            w.told = w.problem
            text = (
                f"Wait: no link to the ECU yet ({w.problem[:200]}). Check that the CAN adapter is plugged in and its "
                "interface up; trial 1 starts as soon as the bridge reads the ECU."
            )
            self.get_logger().warning(text)
            self.pub_trial.publish(self._waiting_msg(text, w.problem))
        if w.future is None and now >= w.next_ask and self.read_client.service_is_ready():
            w.future = self.read_client.call_async(ReadCalibration.Request())
            w.asked = now
            w.next_ask = now + 1.0
        return False

    def _waiting_msg(self, instruction: str, reason: str) -> Trial:
        c = self.campaign
        return self._trial_msg(
            TrialStatus(
                campaign_id=c.cfg.campaign_id,
                trial_id=0,
                attempt=0,
                state=State.IDLE,
                kind=Kind.OPTIMIZED,
                params={},
                budget=c.cfg.budget,
                trials_done=c.trials_done,
                last_j=math.nan,
                best_j=math.nan,
                best_trial_id=0,
                predicted_j=math.nan,
                predicted_j_std=math.nan,
                instruction=instruction,
                reason=reason,
                stamp=c.clock(),
            )
        )

    def _poll_apply(self) -> None:
        a = self._apply
        if a is None:
            return
        now = time.monotonic()
        if self._apply_future is None:
            if now < self._apply_started:
                return  # waiting before asking again (the ECU was busy)
            if self.client.service_is_ready():
                req = ApplyCalibration.Request()
                req.calibration = Calibration(
                    trial_id=int(a.trial_id), names=list(a.params), values=[float(v) for v in a.params.values()]
                )
                req.timeout_s = float(a.timeout_s)
                self._apply_future = self.client.call_async(req)
                self._apply_started = now
                self._apply_deadline = now + a.timeout_s + 1.0
            elif now > self._apply_deadline:
                self._apply = None
                self._do(
                    self.campaign.on_apply_timeout(
                        a.trial_id,
                        a.apply_try,
                        f"service {SRV_APPLY_CALIBRATION} not available within {self.service_wait_s:g} s "
                        "(is ecu_bridge running?)",
                    )
                )
            return
        fut = self._apply_future
        if fut.done():
            self._apply = None
            self._apply_future = None
            try:
                res = fut.result()
            except Exception as exc:  # the call itself failed (e.g. the service went away)
                self._do(self.campaign.on_apply_timeout(a.trial_id, a.apply_try, f"apply call failed: {exc}"))
                return
            if res is None:
                self._do(self.campaign.on_apply_timeout(a.trial_id, a.apply_try, "apply call returned nothing"))
                return
            applied = {str(n): float(v) for n, v in zip(res.applied.names, res.applied.values, strict=False)}
            self._do(
                self.campaign.on_apply_result(
                    a.trial_id,
                    a.apply_try,
                    bool(res.success),
                    int(res.error_code),
                    str(res.message),
                    applied,
                    float(res.latency_s),
                    int(res.attempts),
                )
            )
        elif now > self._apply_deadline:
            self.client.remove_pending_request(fut)
            self._apply = None
            self._apply_future = None
            self._do(
                self.campaign.on_apply_timeout(
                    a.trial_id, a.apply_try, f"no answer from {SRV_APPLY_CALIBRATION} within {a.timeout_s + 1.0:g} s"
                )
            )

    def _poll_run(self) -> None:
        r = self._run
        if r is None:
            return
        if self.get_clock().now().nanoseconds > self._run_deadline_ns:
            self._run = None
            self._do(self.campaign.on_run_timeout(r.trial_id, r.attempt))

    def _on_score(self, msg: RunScore) -> None:
        with self._lock:
            if self.exit_code is not None or not self._started:
                return
            details = {
                "rms_accel_z": float(msg.rms_accel_z),
                "rms_pitch_rate": float(msg.rms_pitch_rate),
                "weighted_rms_accel_z": float(msg.weighted_rms_accel_z),
                "vdv_accel_z": float(msg.vdv_accel_z),
                "kpi": str(msg.kpi),
            }
            outcomes = {str(n): float(v) for n, v in zip(msg.outcome_names, msg.outcome_values, strict=False)}
            self._do(
                self.campaign.on_score(
                    str(msg.campaign_id),
                    int(msg.trial_id),
                    int(msg.attempt),
                    bool(msg.valid),
                    float(msg.j),
                    str(msg.reason),
                    details,
                    outcomes,
                )
            )

    def destroy_node(self) -> None:
        self.campaign.journal.close()
        super().destroy_node()


class _LinkWait:
    """The wait for the ECU link before trial 1."""

    def __init__(self) -> None:
        self.ok = False
        self.since: float | None = None
        self.future: Any = None
        self.asked = 0.0
        self.next_ask = 0.0
        self.problem = ""
        self.told = ""


def main(args: list[str] | None = None) -> int:
    return run_node(BoAgentNode, args)


if __name__ == "__main__":
    sys.exit(main())
