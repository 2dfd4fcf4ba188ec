"""Rescoring: re-cut and re-score recorded runs offline, with the live configuration or a changed one.

No ROS runtime: bags are read with ``rosbags`` (:mod:`bac_measure.bagio`), the
runs go through the same pure cores as the live nodes (ingestion,
:func:`~bac_measure.segmentation.cut_run`, :func:`~bac_measure.kpi.score`).

* A **campaign folder** (``bags/trial_*``, ``journal.jsonl``, ``config/``):
  every run of every trial is cut and scored again with the parameter files
  the campaign was launched with (``config/launch.json``), or with others /
  overrides; the table shows the live J beside the new one. By default the
  recorded ``imu/vehicle`` stream (what the live segmenter got) is re-cut, so
  the same configuration reproduces the live J exactly; ``--reingest`` runs
  ingestion again from ``imu/data_raw`` (to change ingestion parameters).
  A run is found by its (campaign, trial, attempt): a resumed campaign holds
  bags of several launches of the graph, whose sim times overlap (sim time
  starts again with each launch), so the bags are grouped by the launch that
  recorded them (``launches.jsonl``, written by the recorder; for older
  campaigns, the launch of the agent that announced their runs, from the
  journal) and each run is cut from its own launch's data, from its own
  READY_TO_DRIVE announcement there. The live J of a run is the agent's
  verdict in the journal (else the RunScore in the bags). The reference run
  for alignment is the one the live segmenter took (its ``reference.npz``
  names it), rebuilt from its data under the configuration in use; without
  that file, or when that run is invalid now, the first valid run in the live
  order.
* A **bac export** (``bac export CAMPAIGN``'s MDF4, which carries the campaign's trial announcements and files:
  :mod:`bac_campaign.exportio`): scored as the campaign folder it came from, to the same J.
* **Any bag** with sensor_msgs/Imu (rosbag2 mcap/sqlite3, ROS 1) or **MDF file**
  (MDF4 ``.mf4``, MDF 3 ``.mdf``/``.dat`` from INCA, CANape, a data logger; the
  channels by ``--channel-map``/``--channel``, else guessed from units and names,
  :mod:`bac_measure.mdfio`): its IMU is ingested (whole-recording health, mount
  and bias from a standstill, clipping: :mod:`bac_measure.offline`); with
  ``--window whole`` the whole recording is scored as one run (``min_coverage``
  honoured), otherwise it is cut like a bac run starting at its first sample
  (event or distance mode from the parameters; distance mode needs odometry: a
  speed or distance channel of an MDF file).

``--refit`` fits the campaign's GP again on the rescored J values and prints
the new recommendation.

    bac rescore CAMPAIGN_DIR [--params-file F ...] [-p node.param=value ...] [--reingest] [--refit] [--json out.json]
    bac rescore any.bag --window whole [--imu-topic /imu/data] [-p imu_ingest.output_rate_hz=50]
    bac rescore drive.mf4 [--channel-map imu_channels.yaml] [--channel speed=VehSpd] [--window whole]
    bac rescore CAMPAIGN.mf4 [--params-file F ...] [-p ...] [--reingest] [--refit]   # a bac export, as its folder
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from bac_agent.journal import JOURNAL_NAME, journaled_engine_options, read_journal
from bac_campaign.exportio import (
    ExportedBag,
    bag_order,
    export_channels_hint,
    is_bac_export,
    read_manifest,
    unpacked_export,
)
from bac_campaign.launches import launch_of_bags
from bac_common.errors import BacError
from bac_imu.ingest import IngestConfig, ingest_all
from bac_measure.bagio import (
    IMU_TYPE,
    ODOM_TYPE,
    BagError,
    ImuArrays,
    OdomArrays,
    TrialEvent,
    bag_topics,
    read_imu,
    read_messages,
    read_odom,
    read_trials,
    run_starts,
)
from bac_measure.kpi import KpiConfig, Score, score
from bac_measure.mdfio import ChannelMap, MdfError, is_mdf, read_mdf
from bac_measure.measure_config import (
    NODE_IMU_INGEST,
    NODE_KPI_SCORER,
    NODE_RUN_SEGMENTER,
    ParamsFileError,
    check_overrides,
    ingest_config,
    kpi_config,
    load_node_params,
    parse_value,
    segment_config,
)
from bac_measure.offline import OFFLINE_DEFAULTS, fit_rates, whole_recording
from bac_measure.segmentation import (
    ImuSeries,
    OdomSeries,
    Reference,
    RunId,
    Segment,
    SegmentationError,
    SegmentConfig,
    cut_run,
    window_segment,
)

RunKey = tuple[str, int, int]
VEHICLE_TOPIC = "/imu/vehicle"
RAW_TOPIC = "/imu/data_raw"
NS = 1_000_000_000


class RescoreError(BacError, ValueError):
    """Nothing to rescore, or a configuration that cannot be used."""


@dataclass(frozen=True)
class RunResult:
    run: RunId
    params: Mapping[str, float] | None  # the trial's calibration (from the journal), when known
    live_j: float | None  # J the live agent booked (journal) or the scorer published (bag); NaN: invalid; None: neither
    live_reason: str
    segment: Segment
    score: Score

    @property
    def key(self) -> RunKey:
        return (self.run.campaign_id, self.run.trial_id, self.run.attempt)

    @property
    def j(self) -> float:
        return self.score.j if self.score.valid else math.nan

    @property
    def diff(self) -> float:
        if self.live_j is None or math.isnan(self.live_j) or math.isnan(self.j):
            return math.nan
        return self.j - self.live_j


@dataclass
class RescoreResult:
    runs: list[RunResult]
    files: list[Path]
    source: str  # "imu/vehicle (recorded)" or "imu/data_raw (re-ingested)"
    notes: list[str] = field(default_factory=list)
    recommendation: dict[str, Any] | None = None

    def max_abs_diff(self) -> float:
        d = [abs(r.diff) for r in self.runs if not math.isnan(r.diff)]
        return max(d) if d else math.nan


# --- reading ------------------------------------------------------------------------------------------


def campaign_bags(campaign_dir: Path) -> list[Path]:
    bags = (
        sorted(d for d in (campaign_dir / "bags").iterdir() if d.is_dir()) if (campaign_dir / "bags").is_dir() else []
    )
    if not bags:
        raise RescoreError(f"{campaign_dir} holds no trial bags (bags/trial_*)")
    return bags


def default_params_files(campaign_dir: Path | None) -> list[Path]:
    """The parameter files a campaign was launched with (its ``config/``); none otherwise: the nodes' defaults,
    unless the caller gives files (``bac rescore`` gives the car profile's for a foreign bag)."""
    if campaign_dir is not None and (campaign_dir / "config" / "launch.json").exists():
        rec = json.loads((campaign_dir / "config" / "launch.json").read_text())
        return [campaign_dir / "config" / name for name in rec["params_files"]]
    return []


def _merge_order(stamps: list[NDArray[np.int64]]) -> tuple[NDArray[np.int64], NDArray[np.intp]]:
    """Stamps of several recordings merged in time order, a message recorded in two bags counted once:
    (the merged stamps, the index of each into the concatenated parts)."""
    stamp = np.concatenate(stamps)
    order = np.argsort(stamp, kind="stable")
    keep = np.ones(order.shape, bool)
    keep[1:] = np.diff(stamp[order]) != 0
    idx = order[keep]
    return stamp[idx], idx


def _concat_imu(parts: list[ImuArrays]) -> ImuArrays:
    stamp, idx = _merge_order([p.stamp_ns for p in parts])
    return ImuArrays(
        topic=parts[0].topic,
        frame_id=parts[0].frame_id,
        stamp_ns=stamp,
        recv_ns=np.concatenate([p.recv_ns for p in parts])[idx],
        accel=np.concatenate([p.accel for p in parts])[idx],
        gyro=np.concatenate([p.gyro for p in parts])[idx],
    )


def _concat_odom(parts: list[OdomArrays]) -> OdomArrays:
    stamp, idx = _merge_order([p.stamp_ns for p in parts])
    return OdomArrays(
        topic=parts[0].topic,
        frame_id=parts[0].frame_id,
        stamp_ns=stamp,
        recv_ns=np.concatenate([p.recv_ns for p in parts])[idx],
        distance_m=np.concatenate([p.distance_m for p in parts])[idx],
        speed_mps=np.concatenate([p.speed_mps for p in parts])[idx],
        position_y_m=np.concatenate([p.series().position_y_m for p in parts])[idx],
        position_z_m=np.concatenate([p.series().position_z_m for p in parts])[idx],
    )


@dataclass
class _Recording:
    """The data of one launch of the graph (or of bags given by hand), merged in time order."""

    imu_vehicle: ImuArrays | None
    imu_raw: ImuArrays | None
    odom: OdomArrays | None
    starts: list[TrialEvent]  # each run's first READY_TO_DRIVE
    live: dict[RunKey, tuple[float, str]]  # live J (NaN when invalid) and reason
    bags: list[Path] = field(default_factory=list)


@dataclass
class _BagData:
    path: Path
    imu_vehicle: ImuArrays | None
    imu_raw: ImuArrays | None
    odom: OdomArrays | None
    trials: list[TrialEvent]
    live: dict[RunKey, tuple[float, str]]


def read_bag(bag: Path, imu_topic: str | None, odom_topic: str | None) -> _BagData:
    """What one bag holds of a run; a stream the bag lacks is None (a bag opened by a launch that was killed
    before any sample arrived holds only bac/trial), unless the caller named the topic."""
    topics = {"/" + t.lstrip("/"): typ for t, (typ, _) in bag_topics(bag).items()}
    veh = raw = None
    if imu_topic is not None:
        raw = read_imu(bag, imu_topic)
    else:
        if VEHICLE_TOPIC in topics:
            veh = read_imu(bag, VEHICLE_TOPIC)
        if RAW_TOPIC in topics:
            raw = read_imu(bag, RAW_TOPIC)
        elif VEHICLE_TOPIC not in topics and IMU_TYPE in topics.values():
            raw = read_imu(bag)  # the bag's only IMU topic
    odom = None
    if odom_topic is not None or ODOM_TYPE in topics.values():
        try:
            odom = read_odom(bag, odom_topic)
        except BagError:
            if odom_topic is not None:
                raise
    trials = read_trials(bag) if "/bac/trial" in topics else []
    live: dict[RunKey, tuple[float, str]] = {}
    if "/bac/run_score" in topics:
        for _, m in read_messages(bag, "bac/run_score"):
            live[(str(m.campaign_id), int(m.trial_id), int(m.attempt))] = (
                float(m.j) if m.valid else math.nan,
                str(m.reason),
            )
    return _BagData(bag, veh, raw, odom, trials, live)


def merge_bags(parts: Sequence[_BagData]) -> _Recording:
    """One recording of bags that share one clock (one launch), merged in time order."""
    veh = [b.imu_vehicle for b in parts if b.imu_vehicle is not None and len(b.imu_vehicle)]
    raw = [b.imu_raw for b in parts if b.imu_raw is not None and len(b.imu_raw)]
    odo = [b.odom for b in parts if b.odom is not None and len(b.odom.stamp_ns)]
    trials = sorted((e for b in parts for e in b.trials), key=lambda e: (e.stamp_ns, e.recv_ns))
    live: dict[RunKey, tuple[float, str]] = {}
    for b in parts:
        live.update(b.live)
    return _Recording(
        imu_vehicle=_concat_imu(veh) if veh else None,
        imu_raw=_concat_imu(raw) if raw else None,
        odom=_concat_odom(odo) if odo else None,
        starts=run_starts(trials),
        live=live,
        bags=[b.path for b in parts],
    )


def read_recording(
    bags: Sequence[Path],
    imu_topic: str | None,
    odom_topic: str | None,
    channels: ChannelMap | None = None,
    notes: list[str] | None = None,
) -> _Recording:
    """Bags or MDF files that share one clock (one launch, or recordings given by hand) as one recording."""
    parts = []
    for bag in bags:
        if is_mdf(bag):  # an MDF recording: IMU and odometry channels, no bac topics
            try:
                mdf = read_mdf(bag, channels)
            except MdfError as exc:
                hint = export_channels_hint(bag) if channels is None else ""
                if not hint:
                    raise
                raise RescoreError(f"{bag}: {hint}") from exc
            parts.append(_BagData(bag, None, mdf.imu, mdf.odom, [], {}))
            if notes is not None:
                notes.extend(f"{bag.name}: {n}" for n in mdf.notes)
            continue
        if channels is not None and bag.is_file():
            raise RescoreError(f"{bag} is not an MDF file: --channel-map / --channel apply to MDF recordings only")
        parts.append(read_bag(bag, imu_topic, odom_topic))
    if notes is not None:
        for part in parts:
            for imu in (part.imu_vehicle, part.imu_raw):
                note = _steps_back_note(part.path, imu)
                if note:
                    notes.append(note)
    return merge_bags(parts)


def _steps_back_note(path: Path, imu: ImuArrays | None) -> str:
    """A recording whose IMU stamps step back (a clock jump, reordered samples): the offline reading merges every
    stream in time order, where the live chain drops such samples; the note says so rather than hiding it
    (outside review 2026-11-29: a clock jump back of 0.5 s left every figure of the rescoring at 0)."""
    if imu is None or len(imu.stamp_ns) < 2:
        return ""
    step = np.diff(imu.stamp_ns)
    back = imu.stamp_ns[1:] <= np.maximum.accumulate(imu.stamp_ns)[:-1]
    if not back.any():
        return ""
    i = int(np.argmin(step))
    where = (
        f"the largest step back {-step[i] / 1e9:.3f} s at {(imu.stamp_ns[i + 1] - imu.stamp_ns[0]) / 1e9:.3f} s into "
        "the recording"
        if step[i] < 0
        else "equal stamps only"
    )
    return (
        f"{path.name}: {int(back.sum())} IMU sample(s) ({imu.topic}) stamped at or before an earlier one, {where}: "
        "merged in time order here "
        "(equal stamps once), where the live chain drops them; a clock jump back interleaves two stretches of "
        "signal: check the recording's time base (python -m bac_measure.imu_health shows it)"
    )


def _bag_order(bag: Path) -> tuple[int, int, str]:
    """The order a campaign's recorders created its bags (:func:`bac_campaign.exportio.bag_order`)."""
    return bag_order(bag.name)


def journal_verdicts(campaign_dir: Path | None) -> dict[RunKey, tuple[float, str]]:
    """The agent's verdict on each run it booked: J (``trial_scored``) or NaN and the reason (``run_rejected``).
    The live J of a run, even when the recorder missed its RunScore (a graph stopped right after it)."""
    if campaign_dir is None or not (campaign_dir / JOURNAL_NAME).exists():
        return {}
    out: dict[RunKey, tuple[float, str]] = {}
    for e in read_journal(campaign_dir / JOURNAL_NAME).events:
        if e.get("event") in ("trial_scored", "run_rejected") and e.get("attempt") is not None:
            key = (str(e.get("campaign_id")), int(e["trial_id"]), int(e["attempt"]))
            j = e.get("j") if e["event"] == "trial_scored" else None
            out[key] = (float(j) if j is not None else math.nan, str(e.get("reason", "")))
    return out


def journal_runs(campaign_dir: Path | None) -> dict[RunKey, tuple[int, int]]:
    """Each run READY_TO_DRIVE in the journal -> (launch of the agent, counted from 0; the event's seq)."""
    return _journal_launches(campaign_dir)[0]


def _journal_launches(campaign_dir: Path | None) -> tuple[dict[RunKey, tuple[int, int]], dict[int, list[int]]]:
    """(each run -> (launch, seq) as :func:`journal_runs`; each trial id -> the launches that announced it, in
    order: the recorder of each opened one bag for it, trial_NNNN, then trial_NNNN.r1, ...)."""
    if campaign_dir is None or not (campaign_dir / JOURNAL_NAME).exists():
        return {}, {}
    launch = -1
    runs: dict[RunKey, tuple[int, int]] = {}
    trials: dict[int, list[int]] = {}
    for e in read_journal(campaign_dir / JOURNAL_NAME).events:
        kind = e.get("event")
        if kind in ("campaign_started", "campaign_resumed"):
            launch += 1
        elif kind in ("trial_proposed", "apply_requested", "run_ready") and e.get("trial_id") is not None:
            seen = trials.setdefault(int(e["trial_id"]), [])
            if not seen or seen[-1] != launch:
                seen.append(launch)
            if kind == "run_ready":
                key = (str(e.get("campaign_id")), int(e["trial_id"]), int(e["attempt"]))
                runs.setdefault(key, (launch, int(e.get("seq", 0))))
    return runs, trials


def campaign_launches(
    campaign_dir: Path,
    imu_topic: str | None,
    odom_topic: str | None,
    notes: list[str],
    exported: Sequence[ExportedBag] | None = None,
) -> list[_Recording]:
    """The campaign's bags grouped by the launch of the graph that recorded them, each launch merged into one
    recording. A resumed campaign holds several launches whose sim times overlap: a run is cut from its own
    launch's data only. The launch of a bag is the recorder's (``launches.jsonl``); for bags recorded
    before that index existed, the launch of the agent that announced its runs (the journal). ``exported``: the
    bags as read back from a bac export (``campaign_dir`` is then the export's unpacked files)."""
    if exported is not None:
        datas = [_BagData(Path(b.name), b.imu_vehicle, b.imu_raw, b.odom, b.trials, {}) for b in exported]
        if not datas:
            raise RescoreError("the export holds no trial bags (trial_NNNN.* channels)")
    else:
        datas = [read_bag(bag, imu_topic, odom_topic) for bag in campaign_bags(campaign_dir)]
    index = launch_of_bags(campaign_dir)
    runs, trial_launches = _journal_launches(campaign_dir)
    groups: dict[tuple[str, str], list[_BagData]] = {}
    from_journal: list[str] = []
    for data in sorted(datas, key=lambda d: _bag_order(d.path)):
        bag = data.path
        if bag.name in index:
            key = ("recorder", index[bag.name][1])
        else:
            keys = [(e.campaign_id, e.trial_id, e.attempt) for e in run_starts(data.trials)]
            launches = {runs[k][0] for k in keys if k in runs}
            if len(launches) > 1:
                raise RescoreError(
                    f"{bag} holds runs that the journal puts in different launches ({sorted(launches)}): "
                    "the bag or the journal is not this campaign's"
                )
            if not launches:  # no run in it: the n-th bag of a trial is from the n-th launch that announced it
                tid, n, _ = _bag_order(bag)
                announced = trial_launches.get(tid, [])
                if n < len(announced):
                    launches = {announced[n]}
            key = ("agent", str(launches.pop())) if launches else ("bag", bag.name)
            from_journal.append(bag.name)
        groups.setdefault(key, []).append(data)
    if from_journal:
        notes.append(
            f"{len(from_journal)} bags are not in launches.jsonl (recorded before it existed): their launch "
            "is the one whose agent announced their runs (the journal)"
        )
    if len(groups) > 1:
        notes.append(f"{len(groups)} launches (a resumed campaign): each run is cut from its own launch's bags")
    return [merge_bags(parts) for parts in groups.values()]


def journal_params(campaign_dir: Path | None) -> tuple[dict[int, dict[str, float]], dict[str, Any] | None]:
    """Each trial's calibration and the campaign_started event, from the journal (if any)."""
    if campaign_dir is None or not (campaign_dir / JOURNAL_NAME).exists():
        return {}, None
    events = read_journal(campaign_dir / JOURNAL_NAME).events
    params: dict[int, dict[str, float]] = {}
    started = None
    for e in events:
        if e.get("event") == "campaign_started":
            started = e
        if e.get("event") == "trial_proposed" and isinstance(e.get("params"), dict):
            params[int(e["trial_id"])] = {str(k): float(v) for k, v in e["params"].items()}
    return params, started


# --- rescoring -------------------------------------------------------------------------------------------


@dataclass
class _Run:
    start: TrialEvent
    rec: _Recording
    imu: ImuSeries
    odom: OdomSeries

    @property
    def key(self) -> RunKey:
        return (self.start.campaign_id, self.start.trial_id, self.start.attempt)


def rescore(
    paths: Sequence[str | Path],
    files: Sequence[str | Path] | None = None,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    reingest: bool = False,
    window: str = "run",
    imu_topic: str | None = None,
    odom_topic: str | None = None,
    channels: ChannelMap | None = None,
) -> RescoreResult:
    """Cut and score every run of a campaign (or bags, or MDF files) again; see the module doc."""
    if window not in ("run", "whole"):
        raise RescoreError(f"window must be 'run' or 'whole', got {window!r}")
    ps = [Path(p) for p in paths]
    export = exported_campaign(ps)
    if export is None:
        return _rescore(ps, None, files, overrides, reingest, window, imu_topic, odom_topic, channels)
    if channels is not None or imu_topic is not None or odom_topic is not None:
        raise RescoreError(
            f"{export} is a bac export: its channels are known, --channel-map / --channel / --imu-topic / "
            "--odom-topic do not apply"
        )
    with unpacked_export(export) as (folder, bags):
        manifest = read_manifest(folder)
        if reingest and not any(b.imu_raw is not None for b in bags):
            why = (
                "exported with --no-raw; export the campaign again without it, or rescore without --reingest"
                if manifest.get("raw") is False
                else "the campaign recorded none; rescore it without --reingest (the recorded imu/vehicle)"
            )
            raise RescoreError(f"{export} holds no raw IMU (imu/data_raw) for --reingest: {why}")
        try:
            result = _rescore(ps, (folder, bags), files, overrides, reingest, window, None, None, None)
        except BacError as exc:  # name the export, not the temporary folder it was unpacked into
            raise RescoreError(str(exc).replace(f"{folder}/", f"{export}:").replace(str(folder), str(export))) from exc
        # the files inside the export, not the temporary folder they were unpacked into
        result.files = [
            Path(f"{export}:{f.relative_to(folder)}") if f.is_relative_to(folder) else f for f in result.files
        ]
        for skip in manifest.get("skipped", []):
            result.notes.append(
                f"{export}: bag {skip.get('bag')} was left out at export ({skip.get('reason')}): its runs are not "
                "here, and the J of the others may differ from the folder's if it held the reference run"
            )
    return result


def exported_campaign(paths: Sequence[Path]) -> Path | None:
    """The one file given when it is a bac export (``bac export``'s MDF4), scored as its campaign folder."""
    if len(paths) == 1 and paths[0].is_file() and is_bac_export(paths[0]):
        return paths[0]
    if len(paths) > 1 and any(p.is_file() and is_bac_export(p) for p in paths):
        raise RescoreError("a bac export is a whole campaign: rescore it alone (one file), not with other recordings")
    return None


def _rescore(
    ps: list[Path],
    exported: tuple[Path, list[ExportedBag]] | None,
    files: Sequence[str | Path] | None,
    overrides: Mapping[str, Mapping[str, Any]] | None,
    reingest: bool,
    window: str,
    imu_topic: str | None,
    odom_topic: str | None,
    channels: ChannelMap | None,
) -> RescoreResult:
    for p in ps:
        if not p.exists():
            raise RescoreError(f"no such campaign folder or bag: {p}")
        if p.is_dir() and (p / JOURNAL_NAME).is_file() and not (p / "bags").is_dir():
            raise RescoreError(
                f"{p} is a campaign folder without bags/: nothing was recorded to rescore (the recorder "
                "(campaign_recorder) writes bags/trial_NNNN; was it left out of the launch, or the folder copied "
                "without it?)"
            )
    campaign_dir = ps[0] if len(ps) == 1 and (ps[0] / "bags").is_dir() else None
    if exported is not None:
        campaign_dir = exported[0]
    if window == "whole" and campaign_dir is not None:
        raise RescoreError(
            f"--window whole scores one recording as one run; {ps[0]} is a campaign, whose runs are cut by "
            f"its trials: rescore it without --window, or give one trial's bag ({ps[0] / 'bags'}/trial_NNNN) "
            "with --window whole"
            if exported is None
            else f"--window whole scores one recording as one run; {ps[0]} is a bac export of a whole campaign, "
            "whose runs are cut by its trials: rescore it without --window"
        )
    files = [Path(f) for f in files] if files else default_params_files(campaign_dir)
    ov = {k: dict(v) for k, v in (overrides or {}).items()}
    notes: list[str] = []
    for node, values in ov.items():
        if node not in (NODE_IMU_INGEST, NODE_RUN_SEGMENTER, NODE_KPI_SCORER):
            raise RescoreError(f"-p {node}.*: only imu_ingest, run_segmenter and kpi_scorer apply")
        notes += check_overrides(node, values)
    foreign = campaign_dir is None
    ing_ov = dict(ov.get(NODE_IMU_INGEST, {}))
    if foreign:  # a recording that is not a bac campaign: mount and bias from a standstill unless configured
        in_files = load_node_params(files, NODE_IMU_INGEST)
        ing_ov = {**{k: v for k, v in OFFLINE_DEFAULTS.items() if k not in in_files}, **ing_ov}
    ing_cfg = ingest_config(files, ing_ov)
    seg_cfg = segment_config(files, ov.get(NODE_RUN_SEGMENTER))
    kpi_cfg = kpi_config(files, ov.get(NODE_KPI_SCORER))
    if campaign_dir is not None:
        recs = campaign_launches(campaign_dir, imu_topic, odom_topic, notes, exported[1] if exported else None)
    else:
        recs = [read_recording(ps, imu_topic, odom_topic, channels, notes)]
    if not any(r.imu_vehicle is not None or r.imu_raw is not None for r in recs):
        raise RescoreError("the bags hold no IMU stream (imu/vehicle, imu/data_raw or --imu-topic)")

    use_vehicle = not reingest and any(r.imu_vehicle is not None for r in recs)
    problems: dict[int, str] = {}  # a recording whose ingestion left gravity in a_z: no J from it
    source = "imu/vehicle (recorded)"
    series: list[ImuSeries] = []
    for rec in recs:  # ingestion starts again with each launch, as the live imu_ingest did
        if use_vehicle:
            v = rec.imu_vehicle
            series.append(
                ImuSeries(v.stamp_ns, v.accel[:, 2].copy(), v.gyro[:, 1].copy()) if v is not None else ImuSeries.empty()
            )
            continue
        r = rec.imu_raw
        if r is None:
            if rec.starts:
                raise RescoreError(
                    f"{', '.join(str(b) for b in rec.bags)}: no raw IMU stream to ingest (imu/data_raw or --imu-topic)"
                )
            series.append(ImuSeries.empty())
            continue
        source = f"{r.topic} (re-ingested)"
        ing_cfg, seg_cfg = _fit_rates(r, ing_cfg, seg_cfg, ov, notes)
        if foreign:
            ing_cfg, _ = whole_recording(r, ing_cfg, ov.get(NODE_IMU_INGEST, {}), notes)
        out, health = ingest_all(r.stamp_ns, r.accel, r.gyro, ing_cfg)
        series.append(ImuSeries(out.stamp_ns, out.accel_z, out.pitch_rate))
        notes.append(
            f"ingestion: {health.samples_in} samples at {health.rate_hz:.1f} Hz, {health.samples_expected} "
            f"expected, {health.lost_samples} lost, {health.gaps} gaps, {health.out_of_order} out of order, "
            f"{health.duplicates} duplicates, {health.nonfinite} NaN/inf, "
            f"{health.saturated} saturated, {health.restarts} stream restarts, {health.clock_jumps} clock jumps; "
            f"mount roll {health.mount_rpy_deg[0]:.1f} pitch {health.mount_rpy_deg[1]:.1f} deg from "
            f"{health.mount_source}, bias from {health.bias_source}"
        )
        problems[id(rec)] = health.gravity_problem()
    notes[:] = list(dict.fromkeys(notes))  # the same note for each launch once
    jparams, _ = journal_params(campaign_dir)

    if window == "whole":
        imu = series[0]
        rid = RunId("rescore", 1, 1)
        seg = window_segment(imu, imu_rate_hz=seg_cfg.imu_rate_hz, run=rid, min_coverage=seg_cfg.min_coverage)
        if seg.valid and seg.coverage < 1.0:
            notes.append(
                f"{(1.0 - seg.coverage) * seg.window_length_s:.2f} s of holes bridged by linear interpolation "
                f"(coverage {seg.coverage:.3f}, min_coverage {seg_cfg.min_coverage:g})"
            )
        sc = _refuse(score(seg, kpi_cfg), problems.get(id(recs[0]), ""))
        return RescoreResult([RunResult(rid, None, None, "", seg, sc)], list(files), source, notes)

    todo: list[_Run] = []
    seen: dict[RunKey, _Recording] = {}
    for rec, imu in zip(recs, series, strict=True):
        odom = rec.odom.series() if rec.odom is not None else OdomSeries.empty()
        starts = rec.starts
        if not starts and campaign_dir is None:
            notes.append("no bac/trial in the bags: one run per recording, from its first IMU sample")
            starts = [TrialEvent(0, int(imu.stamp_ns[0]) if len(imu) else 0, "rescore", 1, 1, 3, "")]
        for st in starts:
            run = _Run(st, rec, imu, odom)
            if run.key in seen:
                raise RescoreError(
                    f"run {RunId(*run.key)} was announced in two recordings ({', '.join(map(str, seen[run.key].bags))} "
                    f"and {', '.join(map(str, rec.bags))}): these bags are not one campaign's"
                )
            seen[run.key] = rec
            todo.append(run)
    # the live order: the journal's (a resumed campaign's launches overlap in time), else each recording's own
    jruns = journal_runs(campaign_dir)
    todo = [r for _, r in sorted(enumerate(todo), key=lambda kr: (jruns.get(kr[1].key, (0, 1 << 62))[1], kr[0]))]

    template = _segmenter_template(files, ov.get(NODE_RUN_SEGMENTER))
    refs = _references(todo, seg_cfg, Reference.load(template) if template else None, campaign_dir, files, ov, notes)
    verdicts = journal_verdicts(campaign_dir)
    runs: list[RunResult] = []
    for k, run in enumerate(todo):
        ref_at, ref = refs.get(run.start.campaign_id, (len(todo), None))
        # runs up to the reference run were cut live before there was a reference
        seg = cut_run(run.imu, run.odom, seg_cfg, run.start.stamp_ns, ref if k > ref_at else None, RunId(*run.key))
        live = verdicts.get(run.key) or run.rec.live.get(run.key)
        runs.append(
            RunResult(
                run=RunId(*run.key),
                params=jparams.get(run.start.trial_id),
                live_j=None if live is None else live[0],
                live_reason="" if live is None else live[1],
                segment=seg,
                score=_refuse(score(seg, kpi_cfg), problems.get(id(run.rec), "")),
            )
        )
    return RescoreResult(runs, list(files), source, notes)


def _refuse(sc: Score, problem: str) -> Score:
    """No J when the ingestion left gravity in a_z (a wrong mount): the reason names the likely cause."""
    if not problem or not sc.valid:
        return sc
    return dataclasses.replace(sc, j=math.nan, valid=False, reason=f"ingestion: {problem}")


def _references(
    todo: Sequence[_Run],
    seg_cfg: SegmentConfig,
    template: Reference | None,
    campaign_dir: Path | None,
    files: Sequence[Path],
    ov: Mapping[str, Mapping[str, Any]],
    notes: list[str],
) -> dict[str, tuple[int, Reference]]:
    """The alignment reference of each campaign, as live: (index in ``todo`` after which runs are aligned with
    it, the reference). A template when one is configured (every run aligned); else the run the live segmenter
    made the reference (its reference file names it), rebuilt from its own data under the configuration in
    use; else (no such file, or that run is invalid now) the first valid run in the live order."""
    out: dict[str, tuple[int, Reference]] = {}
    for cid in dict.fromkeys(r.start.campaign_id for r in todo):
        if template is not None:
            out[cid] = (-1, template)
            continue
        mine = [(k, r) for k, r in enumerate(todo) if r.start.campaign_id == cid]
        live_ref = _live_reference_run(campaign_dir, cid, files, ov)
        if live_ref is not None:
            mine.sort(key=lambda kr: kr[1].key != live_ref)  # that run first, then the live order
        for k, r in mine:
            seg = cut_run(r.imu, r.odom, seg_cfg, r.start.stamp_ns, None, RunId(*r.key))
            if seg.valid:
                out[cid] = (k, Reference.from_segment(seg, seg_cfg))
                break
            if r.key == live_ref:
                notes.append(
                    f"the live reference run {RunId(*r.key)} is invalid now ({seg.reason}): the first valid run "
                    "is the reference"
                )
    return out


def _live_reference_run(
    campaign_dir: Path | None, campaign_id: str, files: Sequence[Path], ov: Mapping[str, Mapping[str, Any]]
) -> RunKey | None:
    """The run the live run_segmenter made the campaign's reference (from its reference file), if known."""
    if campaign_dir is None:
        return None
    from bac_measure.measure_config import load_node_params

    name = str(load_node_params(files, NODE_RUN_SEGMENTER, ov.get(NODE_RUN_SEGMENTER)).get("reference_file", "") or "")
    path = Path(name.replace("{campaign_id}", campaign_id or "default")) if name else campaign_dir / "reference.npz"
    if not path.exists():
        return None
    try:
        run = Reference.load(path).run
    except SegmentationError:
        return None
    return (run.campaign_id, run.trial_id, run.attempt) if run.campaign_id == campaign_id else None


def _fit_rates(
    raw: ImuArrays,
    ing: IngestConfig,
    seg: SegmentConfig,
    ov: Mapping[str, Mapping[str, Any]],
    notes: list[str],
) -> tuple[IngestConfig, SegmentConfig]:
    """Keep the ingestion's output rate at or below the recording's rate, and the segmenter's equal to it,
    unless the user set them (:func:`bac_measure.offline.fit_rates`)."""
    ing, fitted = fit_rates(raw, ing, seg, ov.get(NODE_IMU_INGEST, {}), ov.get(NODE_RUN_SEGMENTER, {}), notes)
    assert fitted is not None
    return ing, fitted


def _segmenter_template(files: Sequence[Path], overrides: Mapping[str, Any] | None) -> str:
    """run_segmenter's template_file parameter (a stored reference used instead of the first valid run)."""
    from bac_measure.measure_config import load_node_params

    return str(load_node_params(files, NODE_RUN_SEGMENTER, overrides).get("template_file", "") or "")


def refit(campaign_dir: Path, runs: Sequence[RunResult]) -> dict[str, Any]:
    """Fit the campaign's GP on the rescored J of each trial and recommend by the campaign's rule (recommend_rule)."""
    from bac_agent.bo import Engine, EngineConfig
    from bac_common.paramspace import CalibrationDefinition

    _, started = journal_params(campaign_dir)
    if started is None or not started.get("definition"):
        raise RescoreError(f"{campaign_dir}: the journal does not say which parameters were tuned")
    definition = CalibrationDefinition.from_dict(started["definition"])
    # the live campaign's model and recommendation rule
    cfg = EngineConfig.from_dict(
        {**journaled_engine_options(started), "budget": max(1, len(runs)), "seed": int(started.get("seed", 0))}
    )
    eng = Engine(definition, cfg)
    # the outcomes the live agent was told with each trial (a travel sensor's, the simulator's), and over them
    # what the rescore measured again: the outcome limits' models learn as the agent's did
    # (by run: a rejected attempt's own outcomes were never told, and one measurement is not told twice)
    live: dict[tuple[int, int], dict[str, float]] = {}
    for e in read_journal(campaign_dir / JOURNAL_NAME).events:
        tid, attempt = e.get("trial_id"), e.get("attempt", 1)
        if e.get("event") == "trial_scored" and isinstance(e.get("outcomes"), dict) and isinstance(tid, int):
            live[(tid, int(attempt) if isinstance(attempt, int) else 1)] = {
                str(k): float(v)
                for k, v in e["outcomes"].items()
                if isinstance(v, int | float) and not isinstance(v, bool)
            }
    told = 0
    for r in runs:
        if r.params is not None and r.score.valid:
            rescored = {str(k): float(v) for k, v in r.score.outcomes.items() if math.isfinite(v)}
            outcomes = {**live.get((r.run.trial_id, r.run.attempt), {}), **rescored}
            eng.tell(dict(r.params), r.score.j, outcomes)
            told += 1
    if told == 0:
        raise RescoreError("no valid rescored run with known parameters: nothing to fit")
    rec = eng.recommend()
    return {
        "params": dict(rec.params),
        "predicted_j": rec.predicted_j,
        "predicted_std": rec.predicted_std,
        "n_observations": told,
    }


# --- command line ------------------------------------------------------------------------------------------


def _fmt(x: float | None, width: int = 10) -> str:
    if x is None:
        return f"{'-':>{width}}"
    if math.isnan(x):
        return f"{'invalid':>{width}}"
    return f"{x:{width}.6f}"


def format_table(result: RescoreResult) -> str:
    lines = [
        f"source: {result.source}",
        "parameters: " + ", ".join(str(f) for f in result.files),
        *(f"note: {n}" for n in result.notes),
        "",
        f"{'trial':>5} {'att':>3}  {'live J':>10}  {'rescored J':>10}  {'diff':>9}  calibration / reason",
    ]
    for r in result.runs:
        params = " ".join(f"{k}={v:.4g}" for k, v in list((r.params or {}).items())[:4])
        parts = f"RMS a_z {r.score.rms_accel_z:.4f} m/s^2, RMS pitch rate {r.score.rms_pitch_rate:.4f} rad/s"
        what = (params or parts) if r.score.valid else r.score.reason
        diff = f"{r.diff:9.2e}" if not math.isnan(r.diff) else f"{'-':>9}"
        lines.append(f"{r.run.trial_id:5d} {r.run.attempt:3d}  {_fmt(r.live_j)}  {_fmt(r.j)}  {diff}  {what}")
    d = result.max_abs_diff()
    if not math.isnan(d):
        lines.append(f"\nlargest |rescored - live| = {d:.3e}")
    if result.recommendation:
        rec = result.recommendation
        params = " ".join(f"{k}={v:.4g}" for k, v in rec["params"].items())
        lines.append(
            f"recommendation (GP refit on {rec['n_observations']} rescored trials): {params}, "
            f"predicted J {rec['predicted_j']:.4f} ± {rec['predicted_std']:.4f}"
        )
    return "\n".join(lines)


def to_json(result: RescoreResult) -> dict[str, Any]:
    def num(x: float | None) -> float | None:
        return None if x is None or math.isnan(x) else float(x)

    return {
        "source": result.source,
        "params_files": [str(f) for f in result.files],
        "notes": result.notes,
        "runs": [
            {
                "campaign_id": r.run.campaign_id,
                "trial_id": r.run.trial_id,
                "attempt": r.run.attempt,
                "params": dict(r.params) if r.params else None,
                "live_j": num(r.live_j),
                "j": num(r.j),
                "valid": r.score.valid,
                "reason": r.score.reason,
                "rms_accel_z": num(r.score.rms_accel_z),
                "rms_pitch_rate": num(r.score.rms_pitch_rate),
                "lag_s": num(r.segment.lag_s),
                "alignment_score": num(r.segment.alignment_score),
                "mean_speed_mps": num(r.segment.mean_speed_mps),
            }
            for r in result.runs
        ],
        "recommendation": result.recommendation,
    }


def parse_override(text: str) -> tuple[str, str, Any]:
    """``node.param=value`` (or ``:=``) -> (node, param, value parsed as YAML)."""
    sep = ":=" if ":=" in text else "="
    if sep not in text or "." not in text.split(sep, 1)[0]:
        raise argparse.ArgumentTypeError(f"expected node.param=value, got {text!r}")
    key, raw = text.split(sep, 1)
    node, param = key.split(".", 1)
    try:
        return node.strip(), param.strip(), parse_value(raw)
    except ParamsFileError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def main(argv: Sequence[str] | None = None, profile_params: Callable[[str], list[Path]] | None = None) -> int:
    """``bac rescore``; ``profile_params(name)`` gives a graph profile's parameter files (``bac_bringup``): the
    ``sim`` profile's for a campaign folder without its ``config/``, the ``car`` profile's for other bags."""
    ap = argparse.ArgumentParser(
        prog="bac rescore", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("paths", nargs="+", help="a campaign folder, or bags (rosbag2 folder/mcap/db3, ROS 1 .bag)")
    ap.add_argument(
        "--params-file",
        action="append",
        default=[],
        type=Path,
        help="parameter YAML (repeatable; default: the campaign's config/, else the sim profile's for a campaign "
        "folder and the car profile's for other bags)",
    )
    ap.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        type=parse_override,
        metavar="NODE.PARAM=VALUE",
        help="change one parameter of imu_ingest, run_segmenter or kpi_scorer (repeatable)",
    )
    ap.add_argument(
        "--reingest", action="store_true", help="ingest imu/data_raw again instead of the recorded imu/vehicle"
    )
    ap.add_argument(
        "--window",
        choices=("run", "whole"),
        default="run",
        help="run: cut each run like the live segmenter; whole: score each recording as one window",
    )
    ap.add_argument("--imu-topic", help="IMU topic of a foreign bag (default: its only sensor_msgs/Imu topic)")
    ap.add_argument("--odom-topic", help="odometry topic of a foreign bag (default: vehicle/odom or its only one)")
    ap.add_argument(
        "--channel-map",
        type=Path,
        help="MDF files: a YAML mapping roles (accel_x ... gyro_z, speed, distance) to channels",
    )
    ap.add_argument(
        "--channel",
        action="append",
        default=[],
        metavar="ROLE=NAME",
        help="MDF files: map one role to a channel, e.g. speed=VehSpd (repeatable; wins over --channel-map)",
    )
    ap.add_argument("--refit", action="store_true", help="fit the GP again on the rescored J and recommend")
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    overrides: dict[str, dict[str, Any]] = {}
    for node, param, value in args.param:
        if node not in (NODE_IMU_INGEST, NODE_RUN_SEGMENTER, NODE_KPI_SCORER):
            sys.stderr.write(f"bac rescore: -p {node}.{param}: only imu_ingest, run_segmenter and kpi_scorer apply\n")
            return 2
        overrides.setdefault(node, {})[param] = value
    files = list(args.params_file)
    try:
        export = exported_campaign([Path(p) for p in args.paths])
        if not files and profile_params is not None:
            first = Path(args.paths[0])
            is_campaign = len(args.paths) == 1 and (first / "bags").is_dir()
            if export is not None:
                with unpacked_export(export, bags_too=False) as (folder, _):
                    if not default_params_files(folder):
                        files = profile_params("sim")
            elif not (is_campaign and default_params_files(first)):
                files = profile_params("sim" if is_campaign else "car")
        result = rescore(
            args.paths,
            files=files or None,
            overrides=overrides,
            reingest=args.reingest,
            window=args.window,
            imu_topic=args.imu_topic,
            odom_topic=args.odom_topic,
            channels=ChannelMap.load(args.channel_map, args.channel),
        )
        if args.refit and export is not None:
            with unpacked_export(export, bags_too=False) as (folder, _):
                result.recommendation = refit(folder, result.runs)
        elif args.refit:
            result.recommendation = refit(Path(args.paths[0]), result.runs)
    except BacError as exc:
        sys.stderr.write(f"bac rescore: {exc}\n")
        return 2
    sys.stdout.write(format_table(result) + "\n")
    if args.json:
        from bac_measure.imu_health import jsonable

        args.json.write_text(json.dumps(jsonable(to_json(result)), indent=2, allow_nan=False))
    return 0


__all__ = ["KpiConfig", "RescoreResult", "RunResult", "SegmentConfig", "main", "refit", "rescore"]


if __name__ == "__main__":
    sys.exit(main())
