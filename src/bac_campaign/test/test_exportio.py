"""bac rescore CAMPAIGN.mf4: a campaign exported by ``bac export`` is scored from the one file as from its folder:
every run from its own launch (a resumed campaign's sim times overlap), the agent's verdicts, the live reference;
files that only claim to be an export are refused with the reason."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from asammdf import MDF
from test_rescore_launches import CID, RUNS, by_key, make_campaign, write_bag

from bac_campaign.bagplay import BagReadError, expand_bag_paths
from bac_campaign.export import export_mf4
from bac_campaign.exportio import ATTACHMENT_MARK, ExportReadError, is_bac_export, read_export
from bac_campaign.rescore import RescoreError, main, rescore
from bac_common.errors import BacError
from bac_common.paramspace import CalibrationDefinition
from bac_common.paths import resolve_definition
from bac_measure.mdfio import ChannelMap, write_mdf
from bac_measure.measure_config import segment_config
from bac_measure.segmentation import Reference


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The resumed two-launch campaign of test_rescore_launches (its sim times overlap; trial 3's bag holds only
    bac/trial), its live reference run (1, 2), and its export."""
    d = tmp_path_factory.mktemp("export")
    camp = d / CID
    make_campaign(camp)
    journal = camp / "journal.jsonl"
    events = [json.loads(x) for x in journal.read_text().splitlines()]
    for e in events:  # what bac export needs besides: the definition, each trial's calibration
        if e["event"] == "campaign_started":
            e["definition"] = CalibrationDefinition.load(resolve_definition("controller_i")).to_dict()
        if e["event"] == "trial_proposed":
            e["params"] = {"damping_front": 0.1 * e["trial_id"], "damping_rear": 0.5}
    journal.write_text("".join(json.dumps(e) + "\n" for e in events))
    alone = d / "alone"
    write_bag(alone, 1, [(1, 2)])
    Reference.from_segment(by_key(rescore([alone]))[(1, 2)].segment, segment_config([])).save(camp / "reference.npz")
    out = export_mf4(camp, d / "campaign.mf4")
    assert out.files == 3  # journal, launches.jsonl, reference.npz (and the export's manifest)
    return camp, out.path


@pytest.mark.slow
def test_an_export_rescores_as_its_campaign_folder(exported: tuple[Path, Path]) -> None:
    camp, mf4 = exported
    folder = by_key(rescore([camp]))
    assert set(folder) == set(RUNS) and all(r.score.valid for r in folder.values())
    result = rescore([mf4])
    got = by_key(result)
    assert set(got) == set(RUNS)
    for key, r in folder.items():
        assert got[key].j == r.j, key  # bit for bit: the same samples, the same launches, the same reference
        assert got[key].live_j == r.live_j and got[key].params == r.params
    assert [(r.run.trial_id, r.run.attempt) for r in result.runs] == [(1, 1), (1, 2), (2, 1)]  # the live order
    assert any("2 launches" in n for n in result.notes)
    # without the reference file the first valid run would be the reference: it is the export's that counts
    (camp / "reference.npz").rename(camp / "reference.off")
    try:
        other = by_key(rescore([camp]))
    finally:
        (camp / "reference.off").rename(camp / "reference.npz")
    assert other[(2, 1)].j != got[(2, 1)].j


def test_the_export_carries_every_stream_to_the_nanosecond(exported: tuple[Path, Path], tmp_path: Path) -> None:
    from bac_campaign.rescore import read_bag

    camp, mf4 = exported
    assert is_bac_export(mf4)
    bags = {b.name: b for b in read_export(mf4, tmp_path)}
    assert sorted(bags) == ["trial_0001", "trial_0001.r1", "trial_0002", "trial_0003"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "export.json",
        "journal.jsonl",
        "launches.jsonl",
        "reference.npz",
    ]
    assert (tmp_path / "journal.jsonl").read_bytes() == (camp / "journal.jsonl").read_bytes()
    streams = 0
    for name, b in bags.items():
        bag = read_bag(camp / "bags" / name, None, None)
        assert b.trials == bag.trials, name
        for mine, theirs in ((b.imu_raw, bag.imu_raw), (b.imu_vehicle, bag.imu_vehicle)):
            assert (mine is None) == (theirs is None), name
            if mine is not None and theirs is not None:
                streams += 1
                assert np.array_equal(mine.stamp_ns, theirs.stamp_ns)
                assert np.array_equal(mine.accel[:, 2], theirs.accel[:, 2])
                assert np.array_equal(mine.gyro[:, 1], theirs.gyro[:, 1])
        assert (b.odom is None) == (bag.odom is None), name
        if b.odom is not None and bag.odom is not None:
            assert np.array_equal(b.odom.stamp_ns, bag.odom.stamp_ns)
            assert np.array_equal(b.odom.distance_m, bag.odom.distance_m)
            assert np.array_equal(b.odom.speed_mps, bag.odom.speed_mps)
    assert streams == 3  # imu/vehicle of the three bags with runs (the raw IMU: the graph test's campaign)


def test_the_command_line_names_the_files_inside_the_export(
    exported: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    _, mf4 = exported
    assert main([str(mf4)]) == 0
    out = capsys.readouterr().out
    assert "largest |rescored - live|" in out and "/tmp/bac-export-" not in out
    assert main([str(mf4), "--window", "whole"]) == 2
    assert "a bac export of a whole campaign" in capsys.readouterr().err
    assert main([str(mf4), "--channel", "speed=x"]) == 2
    assert "--channel-map / --channel" in capsys.readouterr().err


def test_an_export_is_rescored_alone_and_not_replayed(exported: tuple[Path, Path], tmp_path: Path) -> None:
    camp, mf4 = exported
    with pytest.raises(RescoreError, match="rescore it alone"):
        rescore([mf4, camp / "bags" / "trial_0001"])
    with pytest.raises(BagReadError, match="bac rescore"):
        expand_bag_paths([mf4])
    assert expand_bag_paths([camp / "bags" / "trial_0001"]) == [camp / "bags" / "trial_0001"]


def _with_attachment(src: Path, dst: Path, name: str) -> Path:
    mdf = MDF(src)
    try:
        mdf.attach(b"x", file_name="x", comment=ATTACHMENT_MARK + name)
        mdf.save(dst, overwrite=True)
    finally:
        mdf.close()
    return dst


@pytest.mark.parametrize("name", ["../../escaped.txt", "{tmp}/absolute.txt", "config/../../x", "bags/trial_0001/x"])
def test_an_attachment_outside_the_campaign_folder_is_refused(
    exported: tuple[Path, Path], tmp_path: Path, name: str
) -> None:
    _, mf4 = exported
    name = name.format(tmp=tmp_path)
    bad = _with_attachment(mf4, tmp_path / "bad.mf4", name)
    dest = tmp_path / "unpacked"
    dest.mkdir()
    with pytest.raises(ExportReadError, match="not a campaign file"):
        read_export(bad, dest)
    assert not (dest / name).resolve().exists() and list(dest.iterdir()) == []  # nothing unpacked at all


def test_an_export_without_its_files_is_read_as_any_mdf_file_and_says_so(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    """An export from before 2026-11-29, or one asammdf filtered or cut (both drop the attachments): not taken for
    an export (its channels alone do not make one); without a channel map, the reason and what to do."""
    _, mf4 = exported
    mdf = MDF(mf4)
    try:
        old = mdf.filter(["trial_0002.vehicle.accel_z", "trial_0002.vehicle.pitch_rate"])
        old.save(tmp_path / "old.mf4", overwrite=True)
        old.close()
    finally:
        mdf.close()
    assert not is_bac_export(tmp_path / "old.mf4")
    with pytest.raises(RescoreError, match=r"carries no campaign files.*filtered or cut.*export it again"):
        rescore([tmp_path / "old.mf4"])


def test_other_mdf_files_are_not_exports(tmp_path: Path) -> None:
    from bac_measure.synthetic import bump_run

    run = bump_run(seed=1, t0_ns=10**9)
    t = run.imu.stamp_ns
    from bac_measure.bagio import ImuArrays

    g = np.column_stack([0 * t, 0 * t, run.imu.accel_z + 9.80665])
    plain = write_mdf(tmp_path / "drive.mf4", ImuArrays("imu", "", t, t, g, np.zeros_like(g)))
    assert not is_bac_export(plain)
    mdf3 = write_mdf(tmp_path / "drive.mdf", ImuArrays("imu", "", t, t, g, np.zeros_like(g)), version="3.30")
    assert not is_bac_export(mdf3)  # asammdf refuses to list an MDF 3 file's attachments: that crashed rescore
    assert expand_bag_paths([mdf3]) == [mdf3]
    units = {
        f"{k}_{a}": {"name": f"{k}_{a}", "unit": u} for k, u in (("accel", "m/s^2"), ("gyro", "rad/s")) for a in "xyz"
    }
    assert len(rescore([mdf3], window="whole", channels=ChannelMap.parse(units)).runs) == 1
    shutil.copy(plain, tmp_path / "cut.mf4")
    (tmp_path / "cut.mf4").write_bytes((tmp_path / "cut.mf4").read_bytes()[:200])  # truncated: the reader says why
    assert not is_bac_export(tmp_path / "cut.mf4")
    assert not is_bac_export(tmp_path)


def _attach(dst: Path, items: list[tuple[str, bytes, dict[str, object]]], src: Path | None = None) -> Path:
    mdf = MDF(src) if src is not None else MDF(version="4.10")
    try:
        if src is None:
            from asammdf import Signal

            mdf.append([Signal(np.arange(3.0), np.arange(3.0), name="x")])
        for name, data, kw in items:
            opts: dict[str, Any] = {"file_name": name.replace("/", "__"), **kw}
            mdf.attach(data, comment=ATTACHMENT_MARK + name, **opts)
        mdf.save(dst, overwrite=True)
    finally:
        mdf.close()
    return dst


def test_a_damaged_or_external_attachment_is_refused(tmp_path: Path) -> None:
    """asammdf hands a damaged attachment back as it is (a warning at most) and an external one as b"" or as the
    content of a file elsewhere on this machine: a config lost that way gave every J with the default mount."""
    journal = b'{"seq":0,"event":"campaign_started","campaign_id":"c"}\n' * 20
    good = _attach(tmp_path / "good.mf4", [("journal.jsonl", journal, {"compression": False})])
    raw = good.read_bytes()
    at = raw.index(journal)
    (tmp_path / "bad.mf4").write_bytes(raw[: at + 5] + b"X" + raw[at + 6 :])  # one byte of the journal changed
    dest = tmp_path / "out"
    dest.mkdir()
    assert read_export(good, dest) == [] and (dest / "journal.jsonl").read_bytes() == journal
    with pytest.raises(ExportReadError, match="does not match its MD5 sum"):
        read_export(tmp_path / "bad.mf4", tmp_path / "out")
    secret = tmp_path / "secret.txt"
    secret.write_text("not a campaign file")
    ext = _attach(
        tmp_path / "ext.mf4",
        [("journal.jsonl", journal, {}), ("recommendation.json", b"", {"embedded": False, "file_name": str(secret)})],
    )
    with pytest.raises(ExportReadError, match=r"recommendation\.json is not embedded"):
        read_export(ext, tmp_path / "out")
    twice = _attach(tmp_path / "twice.mf4", [("journal.jsonl", journal, {}), ("journal.jsonl", b"{}", {})])
    with pytest.raises(ExportReadError, match="attached 2 times"):
        read_export(twice, tmp_path / "out")


def test_config_files_of_any_name_travel_and_launch_json_names_only_them(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    camp, _ = exported
    copy = tmp_path / "camp"
    shutil.copytree(camp, copy)
    (copy / "config").mkdir()
    (copy / "config" / "01_sim car+v2 ü.yaml").write_text("run_segmenter:\n  ros__parameters:\n    min_coverage: 0.9\n")
    (copy / "config" / "launch.json").write_text(json.dumps({"params_files": ["01_sim car+v2 ü.yaml"]}))
    out = export_mf4(copy, tmp_path / "c.mf4")
    assert out.files == 5
    dest = tmp_path / "unpacked"
    dest.mkdir()
    read_export(out.path, dest)
    assert (dest / "config" / "01_sim car+v2 ü.yaml").read_text().endswith("0.9\n")
    assert rescore([out.path]).files == [Path(f"{out.path}:config/01_sim car+v2 ü.yaml")]
    # a launch record naming a file outside the export (a path of this machine) is refused, nothing read from it
    (copy / "config" / "launch.json").write_text(json.dumps({"params_files": ["../../etc/x.yaml"]}))
    with pytest.raises(BacError, match=re.escape("lists config/../../etc/x.yaml, which is not in config/")):
        export_mf4(copy, tmp_path / "d.mf4")
    forged = _attach(
        tmp_path / "forged.mf4",
        [
            ("journal.jsonl", (camp / "journal.jsonl").read_bytes(), {}),
            ("config/launch.json", json.dumps({"params_files": ["/etc/passwd"]}).encode(), {}),
        ],
    )
    with pytest.raises(ExportReadError, match=r"names '/etc/passwd', which the export does not carry"):
        rescore([forged])


def test_a_bag_left_out_at_export_is_noted_when_the_export_is_rescored(
    exported: tuple[Path, Path], tmp_path: Path
) -> None:
    camp, _ = exported
    copy = tmp_path / "camp"
    shutil.copytree(camp, copy)
    for f in (copy / "bags" / "trial_0002").iterdir():
        f.write_bytes(b"not a bag")
    out = export_mf4(copy, tmp_path / "c.mf4")
    assert any("trial_0002: skipped" in n for n in out.notes)
    result = rescore([out.path])
    assert any("bag trial_0002 was left out at export" in n for n in result.notes), result.notes
    assert {(r.run.trial_id, r.run.attempt) for r in result.runs} == {(1, 1), (1, 2)}
    with pytest.raises(RescoreError, match=r"holds no raw IMU .* the campaign recorded none"):
        rescore([out.path], reingest=True)
